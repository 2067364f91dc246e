//! Analytic phantoms (2D ellipses, 3D ellipsoids), voxelisation and exact analytic projections.
