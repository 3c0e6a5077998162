"""Fast reasoner: the vector-cache anomaly detection service."""
