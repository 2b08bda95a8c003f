"""Helpers shared by the test tiers: small ONNX graphs, the registry's test fleet, gates and
waits. Test modules import from here, never from one another."""
