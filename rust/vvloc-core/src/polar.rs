//! Polar sampling of a channels-last BEV (DESIGN.md §3 polar grid), bilinear, fill 1 outside.
