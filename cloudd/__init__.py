"""Cloud daemon: serves model suffixes, one standby/service state per robot."""
