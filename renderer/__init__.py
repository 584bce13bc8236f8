"""Neural renderer: rasterizer (moderngl + torch reference), stabilised face crops, neural texture, U-Nets,
training and rendering into the footage (deferred neural rendering, Thies et al. 2019/2020)."""
