"""What comes in from the robot, before estimation: input checks, frames and the world frame,
tool pose histories, the patient's mesh and its registration, and the camera check."""
