//! The cone-beam operator pair with the voxel-driven back projector ([`BackProjector::Voxel`]): the
//! Joseph forward projection of [`Projector3`] and, as its "back" side, FDK's back projection of
//! the unfiltered data ([`back_project_voxels`]), which is not the transpose of the forward
//! projection. Only the conjugate gradients on B A x = B b use it ([`super::cgls::cgls`] with
//! `back_projector: voxel`).
//!
//! [`BackProjector::Voxel`]: super::params::BackProjector::Voxel

use crate::recon::analytic::back_project_voxels;
use crate::recon::control::{Cancel, Control, NoProgress};
use crate::recon::error::ReconError;
use crate::recon::geometry::Views3;
use crate::recon::grid::VolumeGrid;
use crate::recon::projector::{Operator, Projector3};

/// Joseph forward projection, voxel-driven back projection.
#[derive(Debug)]
pub struct VoxelBack3<'a> {
    forward: Projector3<'a>,
    views: &'a Views3,
    grid: &'a VolumeGrid,
}

impl<'a> VoxelBack3<'a> {
    pub fn new(views: &'a Views3, grid: &'a VolumeGrid) -> Self {
        VoxelBack3 {
            forward: Projector3::new(views, grid),
            views,
            grid,
        }
    }
}

impl Operator for VoxelBack3<'_> {
    fn image_len(&self) -> usize {
        self.forward.image_len()
    }
    fn view_count(&self) -> usize {
        self.forward.view_count()
    }
    fn view_len(&self) -> usize {
        self.forward.view_len()
    }
    fn forward(
        &self,
        image: &[f32],
        subset: &[usize],
        out: &mut [f32],
        cancel: &Cancel,
    ) -> Result<(), ReconError> {
        self.forward.forward(image, subset, out, cancel)
    }
    /// The voxel-driven back projection of every view at once (`subset` must list every view in
    /// order: the methods that project subsets use the matched pair).
    fn back(
        &self,
        data: &[f32],
        subset: &[usize],
        image: &mut [f32],
        cancel: &Cancel,
    ) -> Result<(), ReconError> {
        let every = subset.len() == self.views.views.len()
            && subset.iter().enumerate().all(|(i, &v)| i == v);
        if !every {
            return Err(ReconError::param(
                "back_projector",
                "the voxel-driven back projector projects every view at once",
            ));
        }
        let data = ndarray::ArrayView3::from_shape(self.views.shape(), data)
            .map_err(|e| ReconError::param("back_projector", e.to_string()))?;
        let volume = back_project_voxels(
            self.views,
            data,
            self.grid,
            Control::new(cancel, &NoProgress),
        )?;
        for (out, v) in image.iter_mut().zip(volume.iter()) {
            *out = *v;
        }
        Ok(())
    }
    fn ray_dot(&self, view: usize, element: usize, image: &[f32]) -> f32 {
        self.forward.ray_dot(view, element, image)
    }
    fn ray_axpy(&self, view: usize, element: usize, alpha: f32, image: &mut [f32]) {
        self.forward.ray_axpy(view, element, alpha, image)
    }
    fn ray_norm2(&self, view: usize, element: usize) -> f32 {
        self.forward.ray_norm2(view, element)
    }
}
