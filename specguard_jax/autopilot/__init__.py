"""Autopilots: a PX4-style multicopter cascade, an ArduRover-style steering/speed controller, and the mission navigator."""
