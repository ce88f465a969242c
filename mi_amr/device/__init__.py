"""Dr.Jit device code: rays, segment walkers, samplers (point reconstruction),
and delta/ratio tracking. Everything here runs per ray or per sample."""
