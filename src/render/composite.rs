//! Volume rendering: front-to-back compositing of shaded, transfer-function-coloured trilinear samples.

use serde::{Deserialize, Serialize};

use super::bricks::{BrickMask, RayDir, Samples};
use super::clip::Span;
use super::image::{Shade, render_frames};
use super::occupancy::Occupancy;
use super::scene::Scene;
use super::shading::Lighting;
use super::transfer::Lut;
use super::{Clip, RenderError, RgbImage, Sampler, Shading, TransferFunction, V3, ViewRays};

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

/// One ray of a volume rendering part way along: where it is and what it has gathered.
struct March {
    /// Fractional index of the ray's origin and its change per millimetre.
    io: V3,
    id: V3,
    dir: RayDir,
    /// Towards the eye.
    view: [f32; 3],
    /// The span being sampled (an index into the ray's spans) and its ends.
    span: usize,
    t0: f64,
    t1: f64,
    /// The next sample is `t0 + k·step`.
    k: u64,
    /// Samples up to this `t` lie in a busy brick already checked.
    busy_until: f64,
    acc: [f32; 3],
    alpha: f32,
    depth: f32,
}

impl VrShader<'_> {
    /// The march of the ray of pixel (`r`, `c`), its kept spans left in `spans`; `None` when it samples nothing
    /// (it misses the volume's box or the clip keeps none of it).
    #[inline(always)]
    fn start(&self, spans: &mut Vec<Span>, r: usize, c: usize) -> Option<March> {
        let (o, d) = self.rays.ray(r as f64, c as f64);
        let (b0, b1) = self.s.box_interval(o, d)?;
        self.clip.spans(o, d, b0.max(0.0), b1, spans);
        let first = spans.first()?;
        let id = self.s.index_direction(d);
        Some(March {
            io: self.s.index(o),
            id,
            dir: RayDir::new(id),
            view: d.map(|x| -x as f32),
            span: 0,
            t0: first.t0,
            t1: first.t1,
            k: 0,
            busy_until: f64::NEG_INFINITY,
            acc: [0.0; 3],
            alpha: 0.0,
            depth: f32::NAN,
        })
    }

    /// One step of march `m` along its `spans`: a sample, a jump over empty space, or the move to the next span.
    /// `false` once the ray is done (its last span ended or it became opaque).
    #[inline(always)]
    fn advance(&self, m: &mut March, spans: &[Span]) -> bool {
        let t = m.t0 + self.samples.offset(m.k);
        if t > m.t1 {
            m.span += 1;
            let Some(sp) = spans.get(m.span) else {
                return false;
            };
            (m.t0, m.t1, m.k, m.busy_until) = (sp.t0, sp.t1, 0, f64::NEG_INFINITY);
            return true;
        }
        let idx: [f32; 3] = std::array::from_fn(|a| (m.io[a] + t * m.id[a]) as f32);
        if t > m.busy_until {
            let (busy, exit) = self.mask.step(idx, &m.dir);
            if !busy {
                m.k = (m.k + 1).max(self.samples.first_beyond(t + exit, m.t0));
                return true;
            }
            m.busy_until = t + exit;
        }
        m.k += 1;
        let (cell, f) = self.s.cell(idx);
        // A sample in a cell outside the visible window is transparent: not read; nor are the next samples
        // in a block of such cells.
        if let Some(o) = self.cells {
            if !o.block_busy(cell) {
                let exit = t + o.block_exit(idx, cell, &m.dir);
                m.k = m.k.max(self.samples.first_beyond(exit, m.t0));
                return true;
            }
            if !o.busy(cell) {
                return true;
            }
        }
        let v = self.s.at_cell(cell, f);
        if !self.lut.visible(v) {
            return true;
        }
        let [cr, cg, cb, a] = self.lut.get(v);
        if a <= 0.0 {
            return true;
        }
        let g = self.s.gradient(idx);
        let (lit, spec) = self.lighting.light(g.map(|x| x as f32), m.view);
        let w = (1.0 - m.alpha) * a;
        m.acc[0] += w * (cr * lit + spec);
        m.acc[1] += w * (cg * lit + spec);
        m.acc[2] += w * (cb * lit + spec);
        if m.depth.is_nan() {
            m.depth = t as f32;
        }
        m.alpha += w;
        m.alpha < EARLY_TERMINATION
    }

    /// The colour and depth of a finished march.
    #[inline(always)]
    fn finish(&self, m: &March) -> ([f32; 3], f32) {
        (
            std::array::from_fn(|ch| m.acc[ch] + (1.0 - m.alpha) * self.bg[ch]),
            m.depth,
        )
    }

    /// The next pixel of `pixels` whose ray samples something, with its march; the pixels before it (background)
    /// go to `put` at once.
    #[inline(always)]
    fn next_march(
        &self,
        pixels: &mut impl Iterator<Item = (usize, usize)>,
        spans: &mut Vec<Span>,
        put: &mut impl FnMut(usize, usize, [f32; 3], f32),
    ) -> Option<(usize, usize, March)> {
        for (r, c) in pixels {
            match self.start(spans, r, c) {
                Some(m) => return Some((r, c, m)),
                None => put(r, c, self.bg, f32::NAN),
            }
        }
        None
    }
}

impl Shade for VrShader<'_> {
    type Scratch = [Vec<Span>; 2];

    fn scratch(&self) -> Self::Scratch {
        std::array::from_fn(|_| Vec::new())
    }

    #[inline(always)]
    fn shade(&self, scratch: &mut Self::Scratch, r: usize, c: usize) -> ([f32; 3], f32) {
        let spans = &mut scratch[0];
        let Some(mut m) = self.start(spans, r, c) else {
            return (self.bg, f32::NAN);
        };
        while self.advance(&mut m, spans) {}
        self.finish(&m)
    }

    /// Two rays in flight, one step of each in turn: a step is a short chain of dependent operations (position,
    /// brick or cell, a table, the next sample), and the other ray's chain fills its waits. Each ray takes the
    /// same steps as [`Shade::shade`], so the pictures are the same bit for bit. (Two rays written out beat
    /// three or four in a loop over lanes: the loop's own bookkeeping costs more than the overlap gains.)
    #[inline(always)]
    fn shade_pixels(
        &self,
        scratch: &mut Self::Scratch,
        mut pixels: impl Iterator<Item = (usize, usize)>,
        mut put: impl FnMut(usize, usize, [f32; 3], f32),
    ) {
        #[cfg(test)]
        if tests::ONE_RAY.load(std::sync::atomic::Ordering::Relaxed) {
            for (r, c) in pixels {
                let (px, d) = self.shade(scratch, r, c);
                put(r, c, px, d);
            }
            return;
        }
        let [sa, sb] = scratch;
        let mut a = self.next_march(&mut pixels, sa, &mut put);
        let mut b = self.next_march(&mut pixels, sb, &mut put);
        loop {
            match (&mut a, &mut b) {
                (Some((ra, ca, ma)), Some((rb, cb, mb))) => {
                    let live_a = self.advance(ma, sa);
                    let live_b = self.advance(mb, sb);
                    if !live_a {
                        let (px, d) = self.finish(ma);
                        put(*ra, *ca, px, d);
                        a = self.next_march(&mut pixels, sa, &mut put);
                    }
                    if !live_b {
                        let (px, d) = self.finish(mb);
                        put(*rb, *cb, px, d);
                        b = self.next_march(&mut pixels, sb, &mut put);
                    }
                }
                // The pixels have run out: the last ray goes on alone.
                (Some((r, c, m)), None) => {
                    while self.advance(m, sa) {}
                    let (px, d) = self.finish(m);
                    put(*r, *c, px, d);
                    a = None;
                }
                (None, Some((r, c, m))) => {
                    while self.advance(m, sb) {}
                    let (px, d) = self.finish(m);
                    put(*r, *c, px, d);
                    b = None;
                }
                (None, None) => return,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicBool, Ordering};

    use super::*;
    use crate::render::image::tests::{assert_same_picture, noisy_ball};
    use crate::render::{Camera, ClipBox, ClipPlane, Keep, Preset};

    /// Tests set this to render one ray at a time ([`Shade::shade`]) instead of two in flight.
    pub(super) static ONE_RAY: AtomicBool = AtomicBool::new(false);

    #[test]
    fn two_rays_in_flight_render_the_pictures_of_one_ray_at_a_time_bit_for_bit() {
        let vol = noisy_ball();
        let scene = Scene::new(&vol).unwrap();
        let c = scene.centre;
        let clips = [
            Clip::default(),
            Clip {
                planes: vec![ClipPlane {
                    point_mm: c,
                    normal: [0.2, 1.0, -0.3],
                }],
                boxes: vec![],
            },
            // A box cut out of the middle: rays through it sample two spans.
            Clip {
                planes: vec![],
                boxes: vec![ClipBox {
                    centre_mm: c,
                    half_size_mm: [6.0, 6.0, 6.0],
                    axes: None,
                    keep: Keep::Outside,
                }],
            },
        ];
        let mut spans_seen = 0;
        for (k, preset) in Preset::ALL.into_iter().enumerate() {
            for (m, clip) in clips.iter().enumerate() {
                let rays = Camera {
                    azimuth_deg: 41.0 * (k + 2 * m) as f64,
                    elevation_deg: 30.0 - 12.0 * m as f64,
                    ..Camera::default()
                }
                .rays(&vol.frame, vol.data.dim(), 53, 39, 4096)
                .unwrap();
                let vr = VrOptions {
                    transfer_function: preset.transfer_function(),
                    shading: Shading::default(),
                    clip: clip.clone(),
                    background: [0.1, 0.2, 0.3],
                    step_mm: None,
                };
                let two = volume_render(&scene, &rays, &vr).unwrap();
                ONE_RAY.store(true, Ordering::Relaxed);
                let one = volume_render(&scene, &rays, &vr);
                ONE_RAY.store(false, Ordering::Relaxed);
                let one = one.unwrap();
                assert_same_picture(&two, &one, &format!("{preset:?}, clip {m}"));
                let shown = two.depth_mm.iter().filter(|d| !d.is_nan()).count();
                assert!(
                    (50..53 * 39 - 50).contains(&shown),
                    "{preset:?}, clip {m}: {shown} pixels show something"
                );
                if m == 2 {
                    let mut spans = Vec::new();
                    for r in 0..39 {
                        for col in 0..53 {
                            let (o, d) = rays.ray(r as f64, col as f64);
                            if let Some((b0, b1)) = scene.sampler.box_interval(o, d) {
                                clip.spans(o, d, b0.max(0.0), b1, &mut spans);
                                spans_seen += usize::from(spans.len() == 2);
                            }
                        }
                    }
                }
            }
        }
        assert!(spans_seen > 100, "{spans_seen} rays of two spans");
    }
}
