"""Host-side acceleration structures (numpy): macrocell grid, bricks, region
trees, SAH kd-tree, cell hashes, and the pipeline that builds them for a medium."""
