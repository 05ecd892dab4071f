"""Triangle-mesh machinery shared by the stages: topology, distances, winding numbers, sampling."""
