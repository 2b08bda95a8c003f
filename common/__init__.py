"""What every elasticfog daemon shares: config, keys, wire codec, sessions, the ONNX partitioner."""
