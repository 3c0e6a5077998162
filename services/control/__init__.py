"""Control loop: quadrotor dynamics, recovery regions, the AESOP MPC (eq. 3), Algorithm 1."""
