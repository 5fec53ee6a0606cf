"""Reports of mateqa: metrics (pure numpy), per-category tables, files and artefacts."""
