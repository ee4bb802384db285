"""Real-hardware drivers implementing the `sim.devices` protocols (RealSense camera, Robotiq 2F-85 gripper)."""
