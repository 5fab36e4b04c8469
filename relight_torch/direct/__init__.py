"""Direct light from a deep framebuffer: the `Relighter` every method composes (it owns the lights,
their transports and the light-group images) and `open_relighter` for a 'direct' cache."""
