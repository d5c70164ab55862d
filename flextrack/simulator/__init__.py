"""The synthetic world and real data in: motion programs, IMU, rendering, sequence folders (docs/simulator.md)."""
