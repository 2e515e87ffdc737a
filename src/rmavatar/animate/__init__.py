"""Driving a trained avatar with motion files and rendering videos (motion, cameras, video writing)."""
