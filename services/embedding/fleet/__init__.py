"""Detector replicas: who is alive, which robots are whose, and following the others' writes.

Who is alive on the bus (``replicas``), which robots are whose (``sharding``), and following
the other replicas' writes to a shared store (``follow``)."""
