"""The flow tests share the Prefect harness and the per-module catalog of ``tests/conftest.py``."""
