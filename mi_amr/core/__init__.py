"""Foundations every folder above reaches downward: the sortable keys of
blocks (`block_keys`) and the Dr.Jit structs of device data (`jit_struct`).
Nothing here imports the rest of mi-amr."""
