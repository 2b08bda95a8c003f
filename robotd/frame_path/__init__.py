"""A frame's path through the robot daemon: the frame loop, offloaded calls, local runs,
pacing, pipelining, pool turns, hedging, probes and the link to the registry."""
