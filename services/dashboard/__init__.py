"""The dashboard: the flight, the plan tree, the anomaly score and the reasoner, live in a page."""
