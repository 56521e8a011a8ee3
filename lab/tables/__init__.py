"""The results tables of the READMEs (`python -m lab.table`), by role: `catalogue` (which
run folders make which rows), `statistics` (values from the records, seed statistics, paired
differences, verdicts) and `render` (the Markdown); each imports only those before it."""
