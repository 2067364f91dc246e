//! Pure series-to-volume assembly: sort slices along the normal, check spacing, tilt and gaps, rescale to HU, patient coordinates.
