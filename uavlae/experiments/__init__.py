"""The paper's study on top of the library: run records (records.py), the sweeps' aggregation and
report (report.py, ``uavlae-report``), the heuristics' table, the LLM alone's table and the advice
study. It imports uavlae; no other module of uavlae imports it (tests/test_package.py), so the
library never depends on the study. README.md here says how the sweeps run."""
