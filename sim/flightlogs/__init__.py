"""Real flight logs: format files (``formats/``), the import, identification and prediction."""
