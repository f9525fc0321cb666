"""CoIn's stages, one module per paper stage (`refgs`: the Ref-GS coarse stage)."""
