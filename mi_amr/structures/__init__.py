"""Host-side acceleration structures (numpy): macrocell grid, bricks, region
trees, SAH kd-tree, per-level hash tables; `mi_amr.building` builds them for a medium."""
