"""The one implementation of the rotation, pose, projection and metric math (numpy only)."""
