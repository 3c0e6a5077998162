"""The control loop's pure core (no I/O): dynamics, regions, eq. 3's MPC, Algorithm 1.

The quadrotor and its planning models, recovery regions,
scenarios, eq. 3's MPC, the selection of Y, Algorithm 1 (``aesop``, ``controllers``), the
request's handshake, verdict freshness and what a tick says (``outbox``). No bus, no
HTTP, no threads: the loop and the service around it do the I/O (the layout test says
so)."""
