"""Robot daemon: the per-frame split loop, in rooms: sources/ (frame sources), results/ (where
results go), frame_path/ (a frame's way through the daemon), policies/ (split decisions) and
sim/ (the offline simulator); the daemon, its command, telemetry and metrics beside them."""
