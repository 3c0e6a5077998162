"""The detector's pure core (no I/O): the vector cache, its scores, calibration, drift, evaluation.

The vector cache and its scores (paper eq. 2), calibration, the policy that turns evidence
into a threshold, detection phrases, the index, drift,
adaptation, proposals, evaluation and the domain's errors. Imports nothing of the service
around it and no I/O (no HTTP, no Zenoh, no database): the layout test says so."""
