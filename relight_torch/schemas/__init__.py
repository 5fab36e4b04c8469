"""The codeless USD schema plugin as package data: schema.usda (the source), generatedSchema.usda and
plugInfo.json (generated from it by `python -m relight_torch.schemas.generate`). Read through
`relight_torch.schema.schema_dir()`; this package holds no code that runs on import."""
