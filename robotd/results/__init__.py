"""Where applied frames' results go: the `out/<robot>` publication and ROS 2 topics (result
sinks), MCAP recordings, the application client and the `elasticfog results` command."""
