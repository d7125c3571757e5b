"""Dense fills from sparse LiDAR: the nearest-return fill ``x0`` and the classical IP-Basic prior (docs/design.md section 3)."""
