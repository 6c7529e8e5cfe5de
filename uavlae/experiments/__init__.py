"""The paper's experiments: the sweeps' aggregation (report.py) and the heuristics' table (heuristics_table.py)."""
