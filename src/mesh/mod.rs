//! Surface meshes: marching cubes, smoothing, decimation, measurements and binary STL.
