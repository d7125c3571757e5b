"""Camera geometry: projecting LiDAR into the image, surface normals, nearest-pixel and window searches."""
