"""Registry daemon: the routing information base, the scheduler and the embedded Zenoh router."""
