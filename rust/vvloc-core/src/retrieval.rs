//! Exact descriptor retrieval: top-K and radius queries over L2 distances, with persistence.
