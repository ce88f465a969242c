"""Transfer functions: the host table (`function`) and its Dr.Jit side (`device`)."""
