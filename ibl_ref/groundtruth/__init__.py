"""Ground truth: exact Phong-lobe convolution (Knuth et al. 2014, Eq. 4) by exact, sparse, SH and moment routes with rigorous error bounds, the dispatcher, and Kán et al. (2015) maps."""
