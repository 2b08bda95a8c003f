"""The offline simulator: traces and profiles, the trace-driven replay and `elasticfog sim`."""
