//! A real operator whose forward and back projections are counted, for the tests of the methods. It
//! passes on every call but `line_plans`, so the methods that sweep lines take the whole-image passes.

use std::sync::atomic::{AtomicUsize, Ordering};

use crate::recon::control::Cancel;
use crate::recon::error::ReconError;
use crate::recon::projector::Operator;

pub(super) struct Counted<'a> {
    op: &'a dyn Operator,
    forward: AtomicUsize,
    back: AtomicUsize,
}

impl<'a> Counted<'a> {
    pub(super) fn new(op: &'a dyn Operator) -> Self {
        Counted {
            op,
            forward: AtomicUsize::new(0),
            back: AtomicUsize::new(0),
        }
    }

    /// The forward and back projections run so far.
    pub(super) fn passes(&self) -> (usize, usize) {
        (
            self.forward.load(Ordering::Relaxed),
            self.back.load(Ordering::Relaxed),
        )
    }
}

impl Operator for Counted<'_> {
    fn image_len(&self) -> usize {
        self.op.image_len()
    }
    fn view_count(&self) -> usize {
        self.op.view_count()
    }
    fn view_len(&self) -> usize {
        self.op.view_len()
    }
    fn forward(
        &self,
        image: &[f32],
        s: &[usize],
        out: &mut [f32],
        c: &Cancel,
    ) -> Result<(), ReconError> {
        self.forward.fetch_add(1, Ordering::Relaxed);
        self.op.forward(image, s, out, c)
    }
    fn back(
        &self,
        data: &[f32],
        s: &[usize],
        image: &mut [f32],
        c: &Cancel,
    ) -> Result<(), ReconError> {
        self.back.fetch_add(1, Ordering::Relaxed);
        self.op.back(data, s, image, c)
    }
    fn ray_dot(&self, view: usize, element: usize, image: &[f32]) -> f32 {
        self.op.ray_dot(view, element, image)
    }
    fn ray_axpy(&self, view: usize, element: usize, alpha: f32, image: &mut [f32]) {
        self.op.ray_axpy(view, element, alpha, image)
    }
    fn ray_norm2(&self, view: usize, element: usize) -> f32 {
        self.op.ray_norm2(view, element)
    }
}
