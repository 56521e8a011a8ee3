"""Examples to copy: your own task family (`corridor.py`, docs/custom_tasks.md)."""
