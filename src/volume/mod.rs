//! Image-domain volume operations: slices, MPR, MIP/MinIP/average projections, window/level, resampling, smoothing, PNG encoding.
