"""Reports of experiments: `tables` (text) and `figures` (PNG)."""
