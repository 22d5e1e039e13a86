"""The wave stage of the ray-wave model."""
