//! Matching cost, integer-shift yaw cost curves and the exact continuous yaw minimum.
