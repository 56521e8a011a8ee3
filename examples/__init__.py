"""Examples to copy: your own task family (`corridor.py`, docs/custom_tasks.md); the tasks as
Gymnasium envs stepped with random actions (`gymnasium_random.py`)."""
