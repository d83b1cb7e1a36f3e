"""Thin Prefect tasks: one stage on one shard (or one model). Each reads its config, calls one bat3r_core function
that writes its output atomically, and returns a small JSON record (paths, content hash, counts, failed samples).
Caching, retries and result storage: ``tasks._cache``; one task per GPU: ``tasks._devices``."""
