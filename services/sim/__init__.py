"""The simulated vehicle: a quadrotor's truth and flight controller behind the vehicle
contract."""
