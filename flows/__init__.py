"""Orchestration of mateqa: the only package that imports Prefect. Thin tasks, flows, settings."""
