//! Coarse-to-fine translation hypothesis search (paper's hypothesis verification).
