"""The transfer method's bake (final gather and bounce rows, `bake`), its row layout (`rows`),
its bench adapter and its registry entry (`method`)."""
