"""Deployment: the network-namespace testbed, docker-compose demo and example fleets."""
