//! BEV padding (paper Alg. 1 with corrected fill) and the fused padding + polar sampling kernel.
