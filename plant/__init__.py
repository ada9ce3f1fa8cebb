"""Quadrotor plant: model (eqs 1-5), onboard attitude PID, disturbances; the plant process."""
