//! Analytic reconstruction: parallel FBP, fan-beam FBP (arc and flat, Parker short scan) and FDK.
