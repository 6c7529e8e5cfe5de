"""The paper's experiments: the sweeps' aggregation (report.py) and the comparison table (paper_table.py)."""
