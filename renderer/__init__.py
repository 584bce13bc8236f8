"""Neural renderer: rasterizer, neural texture, U-Nets (built in a later stage)."""
