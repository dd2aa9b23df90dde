//! A small software renderer for looking at results: meshes and point clouds to PNG, no GPU.
//!
//! # Brief overview
//!
//! * The camera is orthographic. A [`View`] gives the direction the camera looks from (`front`:
//!   +z, `side`: +x, `top`: +y, `iso`, or azimuth/elevation in degrees about the y-up axis), and
//!   the picture is fitted to the projected extent of the points.
//! * Meshes are rasterised triangle by triangle (polygons as fans) into a z-buffer, with
//!   Lambert plus ambient shading from a light near the camera. Normals are flat (per face) or
//!   smooth (interpolated area-weighted vertex normals). Both sides of a face are lit, so
//!   inconsistently oriented or open meshes still read well.
//! * Point clouds are drawn as depth-tested discs, shaded by a PCA normal over their nearest
//!   points or coloured by depth.
//! * [`Up`] says which model axis is up: y (the default) or z (LiDAR and robotics data, whose
//!   `top` view then looks straight down); z-up data are turned by −90° about x into the
//!   renderer's y-up frame. [`ColourBy`] gives points (and mesh faces, by their vertices' mean)
//!   a base colour by height, intensity or class before shading.
//!
//! ```text
//!  screen:  (0,0) ──── x ────▶ (width,0)        camera basis: right = up_world × eye (or +x)
//!             │                                               up    = eye × right
//!             y      pixel centre (x+½, y+½)                  depth = p · eye (larger = nearer)
//!             ▼
//! ```

use std::fmt;
use std::io::Write;
use std::path::Path;
use std::str::FromStr;

use glam::{DVec2, DVec3};

use super::{EvalError, check_faces};
use crate::denoise::normals::{face_cross, pca_normals, vertex_normals};
use crate::denoise::{NormalWeighting, origin_of};
use crate::io::AtomicFile;
use crate::neighbours::KnnIndex;
use crate::points::Faces;

/// Largest accepted image side in pixels.
pub const MAX_SIDE: u32 = 16_384;
/// Neighbours of the PCA normals that shade point clouds.
pub const POINT_NORMAL_K: usize = 12;

/// Where the camera looks from.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum View {
    /// From +z, y up.
    Front,
    /// From +x, y up.
    Side,
    /// From +y, looking down, −z up.
    Top,
    /// Azimuth 45°, elevation 35.26° (the isometric direction (1, 1, 1)).
    Iso,
    /// Azimuth about +y from +z towards +x, and elevation towards +y, in degrees.
    Angles {
        /// Azimuth in degrees.
        azimuth: f64,
        /// Elevation in degrees.
        elevation: f64,
    },
}

impl View {
    /// Unit vector from the object towards the camera.
    pub fn eye(self) -> DVec3 {
        let (az, el) = match self {
            View::Front => (0.0, 0.0),
            View::Side => (90.0, 0.0),
            View::Top => (0.0, 90.0),
            View::Iso => (45.0, (1.0 / 3f64.sqrt()).asin().to_degrees()),
            View::Angles { azimuth, elevation } => (azimuth, elevation),
        };
        let (az, el) = (f64::to_radians(az), f64::to_radians(el));
        DVec3::new(el.cos() * az.sin(), el.sin(), el.cos() * az.cos())
    }
}

impl fmt::Display for View {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            View::Front => f.write_str("front"),
            View::Side => f.write_str("side"),
            View::Top => f.write_str("top"),
            View::Iso => f.write_str("iso"),
            View::Angles { azimuth, elevation } => write!(f, "{azimuth},{elevation}"),
        }
    }
}

impl FromStr for View {
    type Err = EvalError;
    /// `front`, `side`, `top`, `iso`, or `AZIMUTH,ELEVATION` in degrees (e.g. `30,20`).
    fn from_str(s: &str) -> Result<View, EvalError> {
        let bad = || EvalError::Param {
            name: "view",
            detail: format!(
                "`{s}` is not front, side, top, iso or AZIMUTH,ELEVATION in degrees (e.g. 30,20)"
            ),
        };
        match s.trim().to_ascii_lowercase().as_str() {
            "front" => Ok(View::Front),
            "side" => Ok(View::Side),
            "top" => Ok(View::Top),
            "iso" => Ok(View::Iso),
            other => {
                let (a, e) = other.split_once(',').ok_or_else(bad)?;
                let azimuth: f64 = a.trim().parse().map_err(|_| bad())?;
                let elevation: f64 = e.trim().parse().map_err(|_| bad())?;
                if !(azimuth.is_finite() && (-90.0..=90.0).contains(&elevation)) {
                    return Err(bad());
                }
                Ok(View::Angles { azimuth, elevation })
            }
        }
    }
}

/// Mesh normals.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Shading {
    /// One normal per face: facets and noise stay visible.
    #[default]
    Flat,
    /// Area-weighted vertex normals interpolated across faces.
    Smooth,
}

/// How point clouds are coloured.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PointShading {
    /// Lambert shading with the PCA normal of the nearest points.
    #[default]
    Normal,
    /// Brightness by depth: near points light, far points dark.
    Depth,
}

/// Which model axis points up on the screen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Up {
    /// +y up (meshes, most graphics formats).
    #[default]
    Y,
    /// +z up (LiDAR, robotics: LAS, PCD, KITTI, nuScenes); `top` then looks down −z.
    Z,
}

impl Up {
    /// The usual up axis of `format`: z for LiDAR and robotics formats, y otherwise.
    pub fn of_format(format: crate::io::Format) -> Up {
        use crate::io::Format;
        match format {
            Format::Las
            | Format::Laz
            | Format::Copc
            | Format::Pcd
            | Format::Kitti
            | Format::Nuscenes
            | Format::Bin(_) => Up::Z,
            _ => Up::Y,
        }
    }

    /// `p` in the renderer's y-up frame (a rotation: z-up data turn by −90° about x).
    fn to_y_up(self, p: DVec3) -> DVec3 {
        match self {
            Up::Y => p,
            Up::Z => DVec3::new(p.x, p.z, -p.y),
        }
    }
}

/// What gives each point (or mesh vertex) its base colour, before shading.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ColourBy {
    /// The height along the up axis, on a blue–green–yellow–red ramp from lowest to highest.
    Height,
    /// A per-point intensity, on the same ramp from its 1st to its 99th percentile.
    Intensity,
    /// A per-point class (ASPRS LAS codes: ground brown, vegetation greens, buildings orange,
    /// noise magenta, water blue; other codes a fixed palette).
    Class,
}

/// What to draw and how.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct RenderOptions {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Camera direction.
    pub view: View,
    /// Mesh normals.
    pub shading: Shading,
    /// Point colouring.
    pub point_shading: PointShading,
    /// Splat radius in pixels; `None` picks one from the point count and image size.
    pub point_radius: Option<f64>,
    /// Fraction of the image left free on each side.
    pub margin: f64,
    /// Background colour.
    pub background: [u8; 3],
    /// Surface colour before shading.
    pub colour: [u8; 3],
    /// Which model axis is up.
    pub up: Up,
    /// Colour by height, intensity or class instead of [`RenderOptions::colour`].
    pub colour_by: Option<ColourBy>,
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions {
            width: 800,
            height: 800,
            view: View::Iso,
            shading: Shading::Flat,
            point_shading: PointShading::Normal,
            point_radius: None,
            margin: 0.05,
            background: [255, 255, 255],
            colour: [170, 190, 215],
            up: Up::Y,
            colour_by: None,
        }
    }
}

impl RenderOptions {
    /// Checks sizes and margins.
    ///
    /// # Errors
    /// [`EvalError::Param`] naming the bad option.
    pub fn validate(&self) -> Result<(), EvalError> {
        let bad = |name, detail: String| Err(EvalError::Param { name, detail });
        if !(1..=MAX_SIDE).contains(&self.width) || !(1..=MAX_SIDE).contains(&self.height) {
            return bad(
                "size",
                format!(
                    "width and height must be in 1..={MAX_SIDE}, got {}×{}",
                    self.width, self.height
                ),
            );
        }
        if !(0.0..0.5).contains(&self.margin) {
            return bad(
                "margin",
                format!("must be in [0, 0.5), got {}", self.margin),
            );
        }
        if let Some(r) = self.point_radius
            && !(r > 0.0 && r <= 256.0)
        {
            return bad("point-radius", format!("must be in (0, 256], got {r}"));
        }
        Ok(())
    }
}

/// An 8-bit RGB image.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Image {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Row-major RGB bytes, top row first.
    pub rgb: Vec<u8>,
}

impl Image {
    /// The colour at (x, y), (0, 0) being the top-left corner.
    ///
    /// # Panics
    /// When (x, y) lies outside the image.
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 3] {
        let i = 3 * (y as usize * self.width as usize + x as usize);
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }

    /// Encodes the image as PNG into `w`.
    ///
    /// # Errors
    /// [`EvalError::Png`] on encoder or write failures.
    pub fn write_png<W: Write>(&self, w: W) -> Result<(), EvalError> {
        let mut enc = png::Encoder::new(w, self.width, self.height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc.write_header()?;
        writer.write_image_data(&self.rgb)?;
        writer.finish()?;
        Ok(())
    }

    /// Writes a PNG file; the file appears only when complete.
    ///
    /// # Errors
    /// Unwritable directory, encoder or write failures.
    pub fn save(&self, path: &Path) -> Result<(), EvalError> {
        let mut file = AtomicFile::create(path)?;
        self.write_png(&mut file)?;
        file.commit()?;
        Ok(())
    }
}

/// Orthographic camera fitted to a point set.
struct Camera {
    eye: DVec3,
    right: DVec3,
    up: DVec3,
    /// Projected centre of the fitted extent.
    centre: DVec2,
    /// Pixels per model unit.
    scale: f64,
    half: DVec2,
    /// Model origin subtracted before projecting (precision for georeferenced data).
    origin: DVec3,
}

impl Camera {
    fn fit(
        points: impl Iterator<Item = DVec3> + Clone,
        origin: DVec3,
        opts: &RenderOptions,
    ) -> Camera {
        let eye = opts.view.eye();
        let mut right = DVec3::Y.cross(eye);
        if right.length_squared() < 1e-12 {
            right = DVec3::X;
        }
        let right = right.normalize();
        let up = eye.cross(right).normalize();
        let (mut lo, mut hi) = (DVec2::splat(f64::INFINITY), DVec2::splat(f64::NEG_INFINITY));
        for p in points {
            let q = p - origin;
            let s = DVec2::new(q.dot(right), q.dot(up));
            lo = lo.min(s);
            hi = hi.max(s);
        }
        let size = DVec2::new(opts.width as f64, opts.height as f64);
        let usable = size * (1.0 - 2.0 * opts.margin);
        let extent = hi - lo;
        let sx = if extent.x > 0.0 {
            usable.x / extent.x
        } else {
            f64::INFINITY
        };
        let sy = if extent.y > 0.0 {
            usable.y / extent.y
        } else {
            f64::INFINITY
        };
        let scale = match sx.min(sy) {
            s if s.is_finite() => s,
            _ => 1.0,
        };
        Camera {
            eye,
            right,
            up,
            centre: (lo + hi) / 2.0,
            scale,
            half: size / 2.0,
            origin,
        }
    }

    /// Screen x, y (pixels, y down) and depth (model units, larger = nearer).
    fn project(&self, p: DVec3) -> DVec3 {
        let q = p - self.origin;
        let s = (DVec2::new(q.dot(self.right), q.dot(self.up)) - self.centre) * self.scale;
        DVec3::new(self.half.x + s.x, self.half.y - s.y, q.dot(self.eye))
    }

    /// A light from above-left of the camera.
    fn light(&self) -> DVec3 {
        (self.eye + 0.4 * self.up - 0.3 * self.right).normalize()
    }
}

/// Colour and depth buffers.
struct Target {
    w: usize,
    h: usize,
    rgb: Vec<u8>,
    depth: Vec<f64>,
}

impl Target {
    fn new(opts: &RenderOptions) -> Target {
        let (w, h) = (opts.width as usize, opts.height as usize);
        let mut rgb = Vec::with_capacity(w * h * 3);
        for _ in 0..w * h {
            rgb.extend_from_slice(&opts.background);
        }
        Target {
            w,
            h,
            rgb,
            depth: vec![f64::NEG_INFINITY; w * h],
        }
    }

    #[inline]
    fn put(&mut self, x: usize, y: usize, z: f64, c: [u8; 3]) {
        let i = y * self.w + x;
        if z > self.depth[i] {
            self.depth[i] = z;
            self.rgb[3 * i..3 * i + 3].copy_from_slice(&c);
        }
    }

    fn into_image(self) -> Image {
        Image {
            width: self.w as u32,
            height: self.h as u32,
            rgb: self.rgb,
        }
    }
}

const AMBIENT: f64 = 0.25;

/// Lambert + ambient with the normal turned towards the camera (two-sided lighting).
fn shade(colour: [u8; 3], n: DVec3, cam: &Camera, light: DVec3) -> [u8; 3] {
    let n = if n.dot(cam.eye) < 0.0 { -n } else { n };
    let k = AMBIENT + (1.0 - AMBIENT) * n.dot(light).max(0.0);
    colour.map(|c| (c as f64 * k).round().clamp(0.0, 255.0) as u8)
}

/// Renders a mesh (`faces` given and non-empty) or a point cloud.
///
/// # Errors
/// Bad options, bad face indices, no finite point to draw.
pub fn render(
    positions: &[DVec3],
    faces: Option<&Faces>,
    opts: &RenderOptions,
) -> Result<Image, EvalError> {
    render_with(positions, faces, None, opts)
}

/// [`render`] with one value per point for [`ColourBy::Intensity`] or [`ColourBy::Class`].
///
/// # Errors
/// As [`render`]; colouring by intensity or class without values (or with a wrong count).
pub fn render_with(
    positions: &[DVec3],
    faces: Option<&Faces>,
    values: Option<&[f64]>,
    opts: &RenderOptions,
) -> Result<Image, EvalError> {
    opts.validate()?;
    let rotated: Vec<DVec3>;
    let positions = if opts.up == Up::Y {
        positions
    } else {
        rotated = positions.iter().map(|&p| opts.up.to_y_up(p)).collect();
        &rotated
    };
    let base = base_colours(positions, values, opts)?;
    let faces = faces.filter(|f| !f.is_empty());
    if let Some(f) = faces {
        check_faces(positions.len(), f)?;
    }
    let finite = || positions.iter().copied().filter(|p| p.is_finite());
    if finite().next().is_none() {
        return Err(EvalError::Empty {
            what: "input",
            detail: "no finite point to render".into(),
        });
    }
    let origin = origin_of(positions);
    Ok(match faces {
        Some(f) => {
            let used = super::referenced(positions.len(), f);
            let pts = positions
                .iter()
                .zip(used)
                .filter(|(p, u)| *u && p.is_finite())
                .map(|(p, _)| *p);
            let cam = Camera::fit(pts, origin, opts);
            render_mesh(positions, f, &cam, opts, &base)
        }
        None => {
            let cam = Camera::fit(finite(), origin, opts);
            render_points(positions, &cam, opts, &base)?
        }
    })
}

/// The ramp of height and intensity colouring, low to high.
const RAMP: [[f64; 3]; 5] = [
    [48.0, 18.0, 160.0],
    [30.0, 130.0, 230.0],
    [60.0, 190.0, 90.0],
    [240.0, 210.0, 40.0],
    [215.0, 40.0, 30.0],
];

/// The ramp colour at `t` in [0, 1].
fn ramp(t: f64) -> [u8; 3] {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = t * (RAMP.len() - 1) as f64;
    let i = (x.floor() as usize).min(RAMP.len() - 2);
    let f = x - i as f64;
    let (a, b) = (RAMP[i], RAMP[i + 1]);
    [0, 1, 2].map(|c| (a[c] + (b[c] - a[c]) * f).round() as u8)
}

/// The colour of ASPRS class `code`.
fn class_colour(code: f64) -> [u8; 3] {
    match code as i64 {
        2 => [150, 110, 60],
        3 => [150, 215, 110],
        4 => [70, 170, 60],
        5 => [20, 110, 30],
        6 => [235, 120, 40],
        7 | 18 => [230, 30, 200],
        9 => [40, 90, 230],
        c => {
            const PALETTE: [[u8; 3]; 6] = [
                [160, 160, 160],
                [90, 200, 200],
                [200, 90, 90],
                [120, 120, 220],
                [220, 200, 120],
                [110, 60, 150],
            ];
            PALETTE[c.rem_euclid(PALETTE.len() as i64) as usize]
        }
    }
}

/// The base colour of every point, before shading.
fn base_colours(
    pos: &[DVec3],
    values: Option<&[f64]>,
    opts: &RenderOptions,
) -> Result<Vec<[u8; 3]>, EvalError> {
    let Some(by) = opts.colour_by else {
        return Ok(vec![opts.colour; pos.len()]);
    };
    let heights: Vec<f64>;
    let v: &[f64] = match (by, values) {
        // Positions are in the y-up frame here.
        (ColourBy::Height, _) => {
            heights = pos.iter().map(|p| p.y).collect();
            &heights
        }
        (_, Some(v)) if v.len() == pos.len() => v,
        (_, Some(v)) => {
            return Err(EvalError::Param {
                name: "colour",
                detail: format!("{} values for {} points", v.len(), pos.len()),
            });
        }
        (_, None) => {
            return Err(EvalError::Param {
                name: "colour",
                detail: format!(
                    "colouring by {} needs a per-point {} field, and the input has none",
                    if by == ColourBy::Class {
                        "class"
                    } else {
                        "intensity"
                    },
                    if by == ColourBy::Class {
                        "classification"
                    } else {
                        "intensity"
                    }
                ),
            });
        }
    };
    if by == ColourBy::Class {
        return Ok(v.iter().map(|&c| class_colour(c)).collect());
    }
    let mut finite: Vec<f64> = v
        .iter()
        .zip(pos)
        .filter(|(x, p)| x.is_finite() && p.is_finite())
        .map(|(x, _)| *x)
        .collect();
    if finite.is_empty() {
        return Ok(vec![opts.colour; pos.len()]);
    }
    finite.sort_by(f64::total_cmp);
    let (lo, hi) = match by {
        ColourBy::Intensity => (
            finite[finite.len() / 100],
            finite[(finite.len() * 99 / 100).min(finite.len() - 1)],
        ),
        _ => (finite[0], finite[finite.len() - 1]),
    };
    let span = if hi > lo { hi - lo } else { 1.0 };
    Ok(v.iter().map(|&x| ramp((x - lo) / span)).collect())
}

fn render_mesh(
    pos: &[DVec3],
    faces: &Faces,
    cam: &Camera,
    opts: &RenderOptions,
    base: &[[u8; 3]],
) -> Image {
    let mut target = Target::new(opts);
    let light = cam.light();
    let screen: Vec<DVec3> = pos.iter().map(|&p| cam.project(p)).collect();
    let vn = match opts.shading {
        Shading::Smooth => vertex_normals(pos, faces, NormalWeighting::Area).normals,
        Shading::Flat => Vec::new(),
    };
    for face in faces.iter() {
        if face.iter().any(|&v| !screen[v as usize].is_finite()) {
            continue;
        }
        let flat = face_cross(pos, face).normalize_or_zero();
        let colour = if opts.colour_by.is_none() {
            opts.colour
        } else {
            let mut sum = [0.0f64; 3];
            for &v in face {
                for (c, s) in sum.iter_mut().enumerate() {
                    *s += f64::from(base[v as usize][c]);
                }
            }
            sum.map(|s| (s / face.len() as f64).round() as u8)
        };
        for i in 1..face.len().saturating_sub(1) {
            let t = [face[0], face[i], face[i + 1]].map(|v| v as usize);
            let s = t.map(|v| screen[v]);
            let normal = |b: [f64; 3]| match opts.shading {
                Shading::Flat => flat,
                Shading::Smooth => {
                    let n = vn[t[0]] * b[0] + vn[t[1]] * b[1] + vn[t[2]] * b[2];
                    n.try_normalize().unwrap_or(flat)
                }
            };
            raster_triangle(&mut target, s, |b| shade(colour, normal(b), cam, light));
        }
    }
    target.into_image()
}

/// Fills the pixels whose centres lie in the screen triangle `s` (either winding), depth-tested
/// with the depth interpolated linearly (exact for an orthographic camera).
fn raster_triangle(target: &mut Target, s: [DVec3; 3], colour: impl Fn([f64; 3]) -> [u8; 3]) {
    let area = (s[1].x - s[0].x) * (s[2].y - s[0].y) - (s[1].y - s[0].y) * (s[2].x - s[0].x);
    if area == 0.0 || !area.is_finite() {
        return;
    }
    let min_x = s.iter().map(|p| p.x).fold(f64::INFINITY, f64::min);
    let max_x = s.iter().map(|p| p.x).fold(f64::NEG_INFINITY, f64::max);
    let min_y = s.iter().map(|p| p.y).fold(f64::INFINITY, f64::min);
    let max_y = s.iter().map(|p| p.y).fold(f64::NEG_INFINITY, f64::max);
    // Pixel (x, y) has its centre at (x + ½, y + ½).
    let x0 = (min_x - 0.5).ceil().max(0.0);
    let x1 = (max_x - 0.5).floor().min(target.w as f64 - 1.0);
    let y0 = (min_y - 0.5).ceil().max(0.0);
    let y1 = (max_y - 0.5).floor().min(target.h as f64 - 1.0);
    if x0 > x1 || y0 > y1 {
        return;
    }
    let edge =
        |a: DVec3, b: DVec3, px: f64, py: f64| (b.x - a.x) * (py - a.y) - (b.y - a.y) * (px - a.x);
    for y in y0 as usize..=y1 as usize {
        let py = y as f64 + 0.5;
        for x in x0 as usize..=x1 as usize {
            let px = x as f64 + 0.5;
            let b = [
                edge(s[1], s[2], px, py) / area,
                edge(s[2], s[0], px, py) / area,
                edge(s[0], s[1], px, py) / area,
            ];
            if b.iter().all(|&w| w >= 0.0) {
                let z = b[0] * s[0].z + b[1] * s[1].z + b[2] * s[2].z;
                let i = y * target.w + x;
                if z > target.depth[i] {
                    target.put(x, y, z, colour(b));
                }
            }
        }
    }
}

fn render_points(
    pos: &[DVec3],
    cam: &Camera,
    opts: &RenderOptions,
    base: &[[u8; 3]],
) -> Result<Image, EvalError> {
    let mut target = Target::new(opts);
    let light = cam.light();
    let count = pos.iter().filter(|p| p.is_finite()).count();
    let radius = opts.point_radius.unwrap_or_else(|| {
        // About half of a closed surface faces the camera, and its projection covers most of the
        // fitted picture: visible points lie about √(1.6·w·h/n) pixels apart. Random points
        // leave holes unless the splats are nearly that wide.
        let spacing = (1.6 * opts.width as f64 * opts.height as f64 / count as f64).sqrt();
        (0.9 * spacing).clamp(1.0, 8.0)
    });
    let screen: Vec<DVec3> = pos.iter().map(|&p| cam.project(p)).collect();
    let colours: Vec<[u8; 3]> = match opts.point_shading {
        PointShading::Normal if count >= 3 => {
            let index = KnnIndex::build(pos, origin_of(pos))?;
            let (lists, _) = index.knn_all(POINT_NORMAL_K.min(count))?;
            let (normals, _) = pca_normals(pos, &lists);
            normals
                .iter()
                .zip(base)
                .map(|(&n, &c)| {
                    if n == DVec3::ZERO {
                        c
                    } else {
                        shade(c, n, cam, light)
                    }
                })
                .collect()
        }
        PointShading::Normal => base.to_vec(),
        PointShading::Depth => {
            let (lo, hi) = screen
                .iter()
                .filter(|s| s.is_finite())
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), s| {
                    (lo.min(s.z), hi.max(s.z))
                });
            screen
                .iter()
                .zip(base)
                .map(|(s, b)| {
                    let t = if hi > lo { (s.z - lo) / (hi - lo) } else { 1.0 };
                    let k = AMBIENT + (1.0 - AMBIENT) * t;
                    b.map(|c| (c as f64 * k).round() as u8)
                })
                .collect()
        }
    };
    let r2 = radius * radius;
    let reach = radius.ceil() as i64;
    for (s, c) in screen.iter().zip(&colours) {
        if !s.is_finite() {
            continue;
        }
        let (cx, cy) = (s.x.floor() as i64, s.y.floor() as i64);
        for y in cy - reach..=cy + reach {
            if y < 0 || y >= target.h as i64 {
                continue;
            }
            for x in cx - reach..=cx + reach {
                if x < 0 || x >= target.w as i64 {
                    continue;
                }
                let d = DVec2::new(x as f64 + 0.5 - s.x, y as f64 + 0.5 - s.y);
                if d.length_squared() <= r2 {
                    target.put(x as usize, y as usize, s.z, *c);
                }
            }
        }
    }
    Ok(target.into_image())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::{Shape, SurfaceSampler};

    fn opts(view: View) -> RenderOptions {
        RenderOptions {
            width: 64,
            height: 48,
            view,
            ..RenderOptions::default()
        }
    }

    /// A z-up ground grid 10 × 10 at z = 0 with a wall 1 high along x = 0.
    fn ground() -> Vec<DVec3> {
        let mut v = Vec::new();
        for i in 0..40 {
            for j in 0..40 {
                v.push(DVec3::new(i as f64 * 0.25, j as f64 * 0.25, 0.0));
            }
        }
        for j in 0..40 {
            for k in 1..5 {
                v.push(DVec3::new(0.0, j as f64 * 0.25, k as f64 * 0.25));
            }
        }
        v
    }

    fn covered(img: &Image, bg: [u8; 3]) -> usize {
        (0..img.height)
            .flat_map(|y| (0..img.width).map(move |x| (x, y)))
            .filter(|&(x, y)| img.pixel(x, y) != bg)
            .count()
    }

    #[test]
    fn issue12_top_view_of_z_up_data_looks_down() {
        let pts = ground();
        let o = RenderOptions {
            up: Up::Z,
            point_radius: Some(2.0),
            ..opts(View::Top)
        };
        let down = render(&pts, None, &o).unwrap();
        let side_on = render(
            &pts,
            None,
            &RenderOptions {
                up: Up::Y,
                ..o.clone()
            },
        )
        .unwrap();
        let (a, b) = (
            covered(&down, o.background),
            covered(&side_on, o.background),
        );
        // Looking down, the ground fills the picture; with y up it is seen edge-on.
        assert!(a > 64 * 48 / 3, "top view of z-up ground covers {a} pixels");
        assert!(a > 2 * b, "{a} vs {b}");
        assert_eq!(Up::of_format(crate::io::Format::Las), Up::Z);
        assert_eq!(Up::of_format(crate::io::Format::Nuscenes), Up::Z);
        assert_eq!(Up::of_format(crate::io::Format::Ply), Up::Y);
    }

    #[test]
    fn issue12_colour_by_height_intensity_and_class() {
        let pts = ground();
        let base = RenderOptions {
            up: Up::Z,
            colour_by: Some(ColourBy::Height),
            point_shading: PointShading::Depth,
            ..opts(View::Front)
        };
        let c = base_colours(&pts, None, &base).unwrap();
        // The ground is the low end of the ramp (blue), the wall top the high end (red).
        assert_eq!(c[0], ramp(0.0));
        assert_eq!(*c.last().unwrap(), ramp(1.0));
        assert!(c[0][2] > c[0][0] && c.last().unwrap()[0] > c.last().unwrap()[2]);
        let o = RenderOptions {
            colour_by: Some(ColourBy::Class),
            ..base.clone()
        };
        let classes: Vec<f64> = pts
            .iter()
            .map(|p| if p.z > 0.0 { 6.0 } else { 2.0 })
            .collect();
        let c = base_colours(&pts, Some(&classes), &o).unwrap();
        assert_eq!(c[0], class_colour(2.0));
        assert_eq!(*c.last().unwrap(), class_colour(6.0));
        assert_ne!(class_colour(2.0), class_colour(6.0));
        let e = render_with(&pts, None, None, &o).unwrap_err().to_string();
        assert!(e.contains("needs a per-point classification field"), "{e}");
        // Intensity: the 1st–99th percentile spans the ramp; an outlier does not flatten it.
        let mut inten: Vec<f64> = (0..pts.len()).map(|i| (i % 100) as f64).collect();
        inten[5] = 1e9;
        let o = RenderOptions {
            colour_by: Some(ColourBy::Intensity),
            ..base
        };
        let c = base_colours(&pts, Some(&inten), &o).unwrap();
        assert_eq!(c[0], ramp(0.0));
        assert_ne!(c[50], c[0]);
        assert_ne!(c[50], ramp(1.0));
        let img = render_with(&pts, None, Some(&inten), &o).unwrap();
        assert!(covered(&img, o.background) > 0);
    }

    #[test]
    fn sphere_fills_the_centre_and_leaves_the_corners() {
        let m = Shape::Sphere.mesh(2).unwrap();
        for shading in [Shading::Flat, Shading::Smooth] {
            for view in [View::Front, View::Top, View::Iso, "30,-20".parse().unwrap()] {
                let o = RenderOptions {
                    shading,
                    ..opts(view)
                };
                let img = render(&m.positions, Some(&m.faces), &o).unwrap();
                assert_eq!(img.rgb.len(), 64 * 48 * 3);
                let bg = o.background;
                assert_ne!(img.pixel(32, 24), bg, "{view} centre");
                for (x, y) in [(0, 0), (63, 0), (0, 47), (63, 47)] {
                    assert_eq!(img.pixel(x, y), bg, "{view} corner");
                }
                // Lit from the camera side: the centre is brighter than the ambient level.
                assert!(img.pixel(32, 24)[0] > (o.colour[0] as f64 * 0.6) as u8);
            }
        }
    }

    #[test]
    fn png_round_trip() {
        let m = Shape::Cube.mesh(2).unwrap();
        let img = render(&m.positions, Some(&m.faces), &opts(View::Iso)).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("cube.png");
        img.save(&path).unwrap();
        let file = std::io::BufReader::new(std::fs::File::open(&path).unwrap());
        let mut reader = png::Decoder::new(file).read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!((info.width, info.height), (64, 48));
        assert_eq!(info.color_type, png::ColorType::Rgb);
        assert_eq!(&buf[..info.buffer_size()], &img.rgb[..]);
    }

    #[test]
    fn point_clouds_splat_with_both_shadings() {
        let m = Shape::Sphere.mesh(2).unwrap();
        let pts: Vec<DVec3> = SurfaceSampler::new(&m.positions, &m.faces, 4000, 0)
            .unwrap()
            .flatten()
            .collect();
        for point_shading in [PointShading::Normal, PointShading::Depth] {
            let o = RenderOptions {
                point_shading,
                ..opts(View::Front)
            };
            let img = render(&pts, None, &o).unwrap();
            assert_ne!(img.pixel(32, 24), o.background);
            assert_eq!(img.pixel(0, 0), o.background);
        }
    }

    #[test]
    fn the_nearer_triangle_wins_in_any_order() {
        let o = opts(View::Front);
        let tri = |z: f64| {
            [
                DVec3::new(0.0, 0.0, z),
                DVec3::new(64.0, 0.0, z),
                DVec3::new(0.0, 48.0, z),
            ]
        };
        let (red, blue) = ([255, 0, 0], [0, 0, 255]);
        for near_first in [false, true] {
            let mut t = Target::new(&o);
            let mut order = [(tri(0.0), red), (tri(1.0), blue)];
            if near_first {
                order.reverse();
            }
            for (s, c) in order {
                raster_triangle(&mut t, s, |_| c);
            }
            let img = t.into_image();
            assert_eq!(img.pixel(5, 5), blue);
            // Outside the triangle (beyond its hypotenuse) stays background.
            assert_eq!(img.pixel(60, 45), o.background);
        }
    }

    #[test]
    fn bad_options_and_inputs_are_errors() {
        let m = Shape::Cube.mesh(1).unwrap();
        let o = RenderOptions {
            width: 0,
            ..RenderOptions::default()
        };
        assert!(matches!(
            render(&m.positions, Some(&m.faces), &o),
            Err(EvalError::Param { name: "size", .. })
        ));
        assert!(render(&[DVec3::NAN], None, &RenderOptions::default()).is_err());
        assert!("sideways".parse::<View>().is_err());
        assert!("10,100".parse::<View>().is_err());
        assert_eq!("Top".parse::<View>().unwrap(), View::Top);
        // A single point still renders.
        let img = render(&[DVec3::ONE], None, &opts(View::Front)).unwrap();
        assert_ne!(img.pixel(32, 24), RenderOptions::default().background);
    }
}
