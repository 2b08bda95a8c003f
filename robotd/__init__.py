"""Robot daemon: frame sources, split-decision policies and the per-frame loop."""
