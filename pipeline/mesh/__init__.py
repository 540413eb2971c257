"""Stage ``mesh``: the trained occupancy's isosurface, cleaned."""
