"""The direct method's bake (deep framebuffer, occluders, object paths) and its bench adapter; the
output helpers every other bake builds on (`bake.prepare_output`, `bake.write_npy`, `bake.shot_tracer`)."""
