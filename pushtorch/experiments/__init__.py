"""Runnable experiments: each module has ``run(cfg, out_dir) -> dict`` and a config in conf/experiment/."""
