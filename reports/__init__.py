"""Report generation: tables and figures from saved results."""
