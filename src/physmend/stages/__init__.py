"""Pipeline stages; each is a module with ``run(cfg, source_run_id) -> run_id``."""
