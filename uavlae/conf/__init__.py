"""The Hydra configs (one group per factory). A package so that Hydra finds them by module,
``pkg://uavlae/conf``, wherever uavlae is installed; the YAML files are its package data."""
