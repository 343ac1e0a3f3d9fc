"""The report's sections beyond the tables: one module per study or question it reads."""
