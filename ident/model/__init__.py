"""The driveline model: stiffness laws, linear baseline, dynamics and simulation."""
