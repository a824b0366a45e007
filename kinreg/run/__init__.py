"""Orchestration and side effects: the pipelines, the stage cache, spill files, workers."""
