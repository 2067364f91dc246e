//! Volume rendering: front-to-back compositing of shaded, transfer-function-coloured trilinear samples.

use serde::{Deserialize, Serialize};

use super::bricks::{BrickMask, RayDir, Samples};
use super::clip::Span;
use super::image::{Shade, render_frames};
use super::occupancy::Occupancy;
use super::scene::Scene;
use super::shading::Lighting;
use super::transfer::Lut;
use super::{Clip, RenderError, RgbImage, Sampler, Shading, TransferFunction, ViewRays};

/// Accumulated opacity at which a ray stops.
pub const EARLY_TERMINATION: f32 = 0.99;

/// What a volume rendering shows besides the camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VrOptions {
    pub transfer_function: TransferFunction,
    pub shading: Shading,
    pub clip: Clip,
    /// RGB 0–1 behind the volume.
    pub background: [f64; 3],
    /// Sample step (mm); default half the smallest spacing.
    pub step_mm: Option<f64>,
}

impl VrOptions {
    pub fn validate(&self) -> Result<(), RenderError> {
        self.transfer_function.validate()?;
        self.shading.validate()?;
        self.clip.validate()?;
        if !self
            .background
            .iter()
            .all(|c| c.is_finite() && (0.0..=1.0).contains(c))
        {
            return Err(RenderError::InvalidParameter {
                name: "background",
                reason: "RGB values within [0, 1]".into(),
            });
        }
        Ok(())
    }
}

/// Ray-cast `scene` for `rays` with `opts`. The depth of a pixel is where its first visible sample lies.
///
/// Samples lie at `t0 + k·step` along each kept span of a ray. Runs of empty bricks (no value with opacity) are
/// crossed in one jump to the first sample beyond them ([`BrickMask::step`](super::bricks)); inside a busy brick
/// the samples go on without looking at the mask again until the ray leaves that brick, and a sample whose cell
/// lies wholly outside the visible window (the scene's occupancy bits) is passed without reading the volume. The
/// gradient, and with it the shading, is computed only for samples with opacity.
pub fn volume_render(
    scene: &Scene<'_>,
    rays: &ViewRays,
    opts: &VrOptions,
) -> Result<RgbImage, RenderError> {
    let mut frames = volume_render_frames(scene, std::slice::from_ref(rays), opts)?;
    frames.pop().ok_or(RenderError::BadVolume)
}

/// [`volume_render`] for each of `rays` (pictures of one size, a turning sequence), rendered together: the
/// volume's tables are prepared once, and the threads go on to the next picture without waiting for the last
/// rows of the one before.
pub fn volume_render_frames(
    scene: &Scene<'_>,
    rays: &[ViewRays],
    opts: &VrOptions,
) -> Result<Vec<RgbImage>, RenderError> {
    opts.validate()?;
    let (width, height) = same_size(rays)?;
    let step = scene.step(opts.step_mm)?;
    let samples = Samples::new(step);
    let tf = &opts.transfer_function;
    let lut = Lut::new(tf, step);
    let window = lut.window();
    let mut key = vec![0, step.to_bits()];
    key.extend(
        tf.points
            .iter()
            .flat_map(|p| [p.value.to_bits(), p.opacity.to_bits()]),
    );
    key.extend(
        window
            .iter()
            .map(|&(a, b)| u64::from(a.to_bits()) << 32 | u64::from(b.to_bits())),
    );
    let prepared = scene.prepared(
        key,
        || {
            scene
                .bricks
                .mask(|lo, hi| tf.max_opacity(lo as f64, hi as f64) > 0.0)
        },
        window,
    );
    let shaders: Vec<VrShader<'_>> = rays
        .iter()
        .map(|rays| VrShader {
            rays,
            s: &scene.sampler,
            clip: &opts.clip,
            mask: &prepared.mask,
            cells: prepared.cells.as_ref(),
            lut: &lut,
            samples,
            lighting: Lighting::new(&opts.shading),
            bg: opts.background.map(|c| c as f32),
        })
        .collect();
    Ok(render_frames(width, height, &shaders))
}

/// The common size of the pictures of `rays`.
pub(crate) fn same_size(rays: &[ViewRays]) -> Result<(usize, usize), RenderError> {
    let size = rays.first().map_or((0, 0), |r| (r.width, r.height));
    if rays.iter().any(|r| (r.width, r.height) != size) {
        return Err(RenderError::InvalidParameter {
            name: "size",
            reason: "the pictures of a sequence have one size".into(),
        });
    }
    Ok(size)
}

/// What [`volume_render`] needs for each pixel.
struct VrShader<'a> {
    rays: &'a ViewRays,
    s: &'a Sampler<'a>,
    clip: &'a Clip,
    mask: &'a BrickMask,
    cells: Option<&'a Occupancy>,
    lut: &'a Lut,
    samples: Samples,
    lighting: Lighting,
    bg: [f32; 3],
}

impl Shade for VrShader<'_> {
    type Scratch = Vec<Span>;

    fn scratch(&self) -> Vec<Span> {
        Vec::new()
    }

    #[inline(always)]
    fn shade(&self, spans: &mut Vec<Span>, r: usize, c: usize) -> ([f32; 3], f32) {
        let (o, d) = self.rays.ray(r as f64, c as f64);
        let Some((b0, b1)) = self.s.box_interval(o, d) else {
            return (self.bg, f32::NAN);
        };
        self.clip.spans(o, d, b0.max(0.0), b1, spans);
        let io = self.s.index(o);
        let id = self.s.index_direction(d);
        let ray_dir = RayDir::new(id);
        let at = |t: f64| -> [f32; 3] { std::array::from_fn(|a| (io[a] + t * id[a]) as f32) };
        let view = d.map(|x| -x as f32);
        let (mut acc, mut alpha, mut depth) = ([0.0f32; 3], 0.0f32, f32::NAN);
        'spans: for sp in spans.iter() {
            let mut k = 0u64;
            // Samples up to this `t` lie in a busy brick already checked.
            let mut busy_until = f64::NEG_INFINITY;
            loop {
                let t = sp.t0 + self.samples.offset(k);
                if t > sp.t1 {
                    break;
                }
                let idx = at(t);
                if t > busy_until {
                    let (busy, exit) = self.mask.step(idx, &ray_dir);
                    if !busy {
                        k = (k + 1).max(self.samples.first_beyond(t + exit, sp.t0));
                        continue;
                    }
                    busy_until = t + exit;
                }
                k += 1;
                let (cell, f) = self.s.cell(idx);
                // A sample in a cell outside the visible window is transparent: not read; nor are the
                // next samples in a block of such cells.
                if let Some(o) = self.cells {
                    if !o.block_busy(cell) {
                        let exit = t + o.block_exit(idx, cell, &ray_dir);
                        k = k.max(self.samples.first_beyond(exit, sp.t0));
                        continue;
                    }
                    if !o.busy(cell) {
                        continue;
                    }
                }
                let v = self.s.at_cell(cell, f);
                if !self.lut.visible(v) {
                    continue;
                }
                let [cr, cg, cb, a] = self.lut.get(v);
                if a <= 0.0 {
                    continue;
                }
                let g = self.s.gradient(idx);
                let (lit, spec) = self.lighting.light(g.map(|x| x as f32), view);
                let w = (1.0 - alpha) * a;
                acc[0] += w * (cr * lit + spec);
                acc[1] += w * (cg * lit + spec);
                acc[2] += w * (cb * lit + spec);
                if depth.is_nan() {
                    depth = t as f32;
                }
                alpha += w;
                if alpha >= EARLY_TERMINATION {
                    break 'spans;
                }
            }
        }
        (
            std::array::from_fn(|ch| acc[ch] + (1.0 - alpha) * self.bg[ch]),
            depth,
        )
    }
}
