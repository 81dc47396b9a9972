"""triangulate stage."""
