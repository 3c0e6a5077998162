"""``aesop bench ...``: the benchmarks.

Nothing here runs in a service. The modules import the services' pure parts
(scoring, eq. 3, the planner) in process, or drive a running stack over Zenoh
and HTTP; their own dependencies (matplotlib, CVXPY, psutil) come with the
``bench`` extra.
"""
