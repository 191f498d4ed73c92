//! Interpolated circular roll (DESIGN.md §3): `roll(D, s)[i] = D[(i - s) mod n]`, linear
//! interpolation between the two neighbouring integer rolls for real `s`.
