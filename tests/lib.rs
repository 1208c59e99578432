//! Helpers of the workspace integration tests (the `[[test]]` files beside this one):
//! finding and running the release `deepstereo` binary, the shared real scenes, random
//! cameras, writers of every scene format the readers accept (so that tests can build
//! scenes, round-trip them and corrupt them), and a minimal safetensors reader.

use deepstereo_core::camera::{Camera, Distortion, Intrinsics, WorldToCamera};
use deepstereo_core::imageio::save_rgb8_png;
use deepstereo_core::scene::npy::{write_npy_f32, write_npy_f64};
use glam::{DMat3, DQuat, DVec3};
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::ffi::OsStr;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Longest a single CLI invocation may run before it counts as a hang.
pub const CLI_TIMEOUT: Duration = Duration::from_secs(120);

/// The `deepstereo` binary of the same target profile as the running test executable
/// (`target/<profile>/deps/<test>` -> `target/<profile>/deepstereo`).
pub fn deepstereo_bin() -> PathBuf {
    let exe = std::env::current_exe().expect("current_exe");
    let profile_dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("the test executable lives in target/<profile>/deps");
    let bin = profile_dir.join(format!("deepstereo{}", std::env::consts::EXE_SUFFIX));
    if !bin.is_file() {
        panic!(
            "{} is missing: build it first: cargo build --release",
            bin.display()
        );
    }
    bin
}

/// The shared real scenes (`../shared/data` from the workspace root), or `None` after
/// printing why the calling test is skipped.
/// The shipped weights of the paper-family preset `tiny` (no longer the embedded default,
/// kept for the tests of that family).
pub fn tiny_asset() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../deepstereo-train/assets/tiny.safetensors")
}

pub fn shared_data() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    if dir.is_dir() {
        Some(dir)
    } else {
        println!(
            "SKIPPED: the shared scenes are absent ({} does not exist)",
            dir.display()
        );
        None
    }
}

/// Runs the binary with `args` and checks that it succeeded (else panics with its
/// standard error).
pub fn ok(args: &[&str]) -> CmdOutput {
    let res = run_deepstereo(args);
    assert_eq!(
        res.code,
        Some(0),
        "deepstereo {} failed:\n{}",
        args.join(" "),
        res.stderr
    );
    res
}

/// What one run of the binary did.
#[derive(Debug)]
pub struct CmdOutput {
    /// `None` when killed by a signal or the timeout.
    pub code: Option<i32>,
    pub stdout: String,
    pub stderr: String,
    pub timed_out: bool,
}

impl CmdOutput {
    /// The first non-empty line of stderr.
    pub fn first_stderr_line(&self) -> &str {
        self.stderr
            .lines()
            .find(|l| !l.trim().is_empty())
            .unwrap_or("")
    }
}

/// Runs `deepstereo` with `args`, killing it after [`CLI_TIMEOUT`].
pub fn run_deepstereo<I, S>(args: I) -> CmdOutput
where
    I: IntoIterator<Item = S>,
    S: AsRef<OsStr>,
{
    let mut out = tempfile::tempfile().expect("temp file");
    let mut err = tempfile::tempfile().expect("temp file");
    let mut child = std::process::Command::new(deepstereo_bin())
        .args(args)
        .stdin(std::process::Stdio::null())
        .stdout(out.try_clone().expect("clone"))
        .stderr(err.try_clone().expect("clone"))
        .spawn()
        .expect("spawn deepstereo");
    let start = Instant::now();
    let (status, timed_out) = loop {
        if let Some(s) = child.try_wait().expect("wait") {
            break (Some(s), false);
        }
        if start.elapsed() > CLI_TIMEOUT {
            let _ = child.kill();
            let _ = child.wait();
            break (None, true);
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let read = |f: &mut std::fs::File| {
        let mut buf = Vec::new();
        f.seek(SeekFrom::Start(0)).expect("seek");
        f.read_to_end(&mut buf).expect("read");
        String::from_utf8_lossy(&buf).into_owned()
    };
    CmdOutput {
        code: status.and_then(|s| s.code()),
        stdout: read(&mut out),
        stderr: read(&mut err),
        timed_out,
    }
}

/// Deterministic pseudo-random numbers (SplitMix64).
pub struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in `[a, b)`.
    pub fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64)
    }
    /// A uniformly random rotation (from a random unit quaternion).
    pub fn rotation(&mut self) -> DMat3 {
        loop {
            let q = DVec3::new(
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
            );
            let w = self.range(-1.0, 1.0);
            let n = (q.length_squared() + w * w).sqrt();
            if n > 0.1 && n <= 1.0 {
                return DMat3::from_quat(DQuat::from_xyzw(q.x / n, q.y / n, q.z / n, w / n));
            }
        }
    }
    /// A random pose whose camera centre lies within `extent` of the origin.
    pub fn pose(&mut self, extent: f64) -> WorldToCamera {
        let r = self.rotation();
        let c = DVec3::new(
            self.range(-extent, extent),
            self.range(-extent, extent),
            self.range(-extent, extent),
        );
        WorldToCamera::new_checked(r, -(r * c)).expect("a random rotation is a rotation")
    }
}

/// Writes a `w x h` PNG of random colours.
pub fn write_png(path: &Path, w: u32, h: u32, seed: u64) {
    let mut rng = Rng(seed);
    let rgb: Vec<u8> = (0..w * h * 3).map(|_| rng.next_u64() as u8).collect();
    save_rgb8_png(path, w, h, &rgb).expect("write PNG");
}

/// A named camera to write into a scene.
#[derive(Clone, Debug)]
pub struct NamedCamera {
    pub name: String,
    pub camera: Camera,
}

/// `n` cameras of the given intrinsics with random poses, named `img_000.png`, ...
pub fn random_cameras(rng: &mut Rng, n: usize, intrinsics: &[Intrinsics]) -> Vec<NamedCamera> {
    (0..n)
        .map(|i| NamedCamera {
            name: format!("img_{i:03}.png"),
            camera: Camera {
                intrinsics: intrinsics[i % intrinsics.len()],
                pose: rng.pose(5.0),
                rolling_shutter: None,
            },
        })
        .collect()
}

/// Writes one random PNG per camera, of its size, as `dir/<name>`.
pub fn write_images(dir: &Path, cams: &[NamedCamera]) {
    std::fs::create_dir_all(dir).expect("mkdir");
    for (i, c) in cams.iter().enumerate() {
        let k = &c.camera.intrinsics;
        write_png(&dir.join(&c.name), k.width, k.height, i as u64 + 1);
    }
}

/// The rows of `poses_bounds.npy` for `cams` (LLFF: `fx == fy`, centred principal point).
pub fn llff_rows(cams: &[NamedCamera], bounds: (f64, f64)) -> Vec<f64> {
    let mut rows = Vec::new();
    for c in cams {
        let k = &c.camera.intrinsics;
        let c2w = c.camera.pose.inverse();
        let (x, y, z) = (
            c2w.rotation.x_axis,
            c2w.rotation.y_axis,
            c2w.rotation.z_axis,
        );
        let (down, right, back, centre) = (y, x, -z, c2w.translation);
        let hwf = [k.height as f64, k.width as f64, k.fx];
        for r in 0..3 {
            rows.extend([down[r], right[r], back[r], centre[r], hwf[r]]);
        }
        rows.extend([bounds.0, bounds.1]);
    }
    rows
}

/// Writes an LLFF scene: `poses_bounds.npy` (`<f8`, or `<f4` when `f32`) and `images/`.
pub fn write_llff(dir: &Path, cams: &[NamedCamera], bounds: (f64, f64), f32: bool) {
    let rows = llff_rows(cams, bounds);
    let path = dir.join("poses_bounds.npy");
    if f32 {
        let v: Vec<f32> = rows.iter().map(|&x| x as f32).collect();
        write_npy_f32(&path, &[cams.len(), 17], &v).expect("write npy");
    } else {
        write_npy_f64(&path, &[cams.len(), 17], &rows).expect("write npy");
    }
    write_images(&dir.join("images"), cams);
}

/// COLMAP camera models: name, binary id.
pub const COLMAP_MODELS: [(&str, i32); 5] = [
    ("SIMPLE_PINHOLE", 0),
    ("PINHOLE", 1),
    ("SIMPLE_RADIAL", 2),
    ("RADIAL", 3),
    ("OPENCV", 4),
];

/// COLMAP's parameters of `k` for `model` (the caller makes `k` fit the model).
pub fn colmap_params(model: &str, k: &Intrinsics) -> Vec<f64> {
    let d = k.distortion.unwrap_or_default();
    match model {
        "SIMPLE_PINHOLE" => vec![k.fx, k.cx, k.cy],
        "PINHOLE" => vec![k.fx, k.fy, k.cx, k.cy],
        "SIMPLE_RADIAL" => vec![k.fx, k.cx, k.cy, d.k1],
        "RADIAL" => vec![k.fx, k.cx, k.cy, d.k1, d.k2],
        _ => vec![k.fx, k.fy, k.cx, k.cy, d.k1, d.k2, d.p1, d.p2],
    }
}

/// Random intrinsics of `w x h` images that `model` can represent exactly.
pub fn intrinsics_for_model(rng: &mut Rng, model: &str, w: u32, h: u32) -> Intrinsics {
    let f = rng.range(5.0, 40.0);
    let mut k = Intrinsics::pinhole(
        f,
        rng.range(5.0, 40.0),
        rng.range(0.0, w as f64),
        rng.range(0.0, h as f64),
        w,
        h,
    );
    let mut d = Distortion::default();
    match model {
        "SIMPLE_PINHOLE" => k.fy = k.fx,
        "PINHOLE" => {}
        "SIMPLE_RADIAL" => {
            k.fy = k.fx;
            d.k1 = rng.range(-0.2, 0.2);
        }
        "RADIAL" => {
            k.fy = k.fx;
            d.k1 = rng.range(-0.2, 0.2);
            d.k2 = rng.range(-0.05, 0.05);
        }
        _ => {
            d = Distortion {
                k1: rng.range(-0.2, 0.2),
                k2: rng.range(-0.05, 0.05),
                p1: rng.range(-0.01, 0.01),
                p2: rng.range(-0.01, 0.01),
            }
        }
    }
    k.distortion = (!d.is_zero()).then_some(d);
    k
}

/// COLMAP's `QW QX QY QZ` of a world-to-camera rotation.
pub fn colmap_quat(r: DMat3) -> [f64; 4] {
    let q = DQuat::from_mat3(&r);
    [q.w, q.x, q.y, q.z]
}

/// Writes a COLMAP text model to `dir/sparse/0/` plus `dir/images/`; camera `i` uses
/// model `models[i % len]` and camera id `i + 1`.
pub fn write_colmap_text(dir: &Path, cams: &[NamedCamera], models: &[&str], points: &[DVec3]) {
    let model = dir.join("sparse/0");
    std::fs::create_dir_all(&model).expect("mkdir");
    let mut cameras = String::from("# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n");
    let mut images = String::from("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n");
    for (i, c) in cams.iter().enumerate() {
        let m = models[i % models.len()];
        let k = &c.camera.intrinsics;
        let params: Vec<String> = colmap_params(m, k).iter().map(|v| v.to_string()).collect();
        cameras += &format!(
            "{} {m} {} {} {}\n",
            i + 1,
            k.width,
            k.height,
            params.join(" ")
        );
        let q = colmap_quat(c.camera.pose.rotation);
        let t = c.camera.pose.translation;
        images += &format!(
            "{} {} {} {} {} {} {} {} {} {}\n",
            i + 1,
            q[0],
            q[1],
            q[2],
            q[3],
            t.x,
            t.y,
            t.z,
            i + 1,
            c.name
        );
        // The 2D points line: one observation of point 1, or none.
        images += if i % 2 == 0 { "1.5 2.5 1\n" } else { "\n" };
    }
    let mut pts = String::from("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n");
    for (i, p) in points.iter().enumerate() {
        pts += &format!("{} {} {} {} 128 128 128 0.5 1 0\n", i + 1, p.x, p.y, p.z);
    }
    std::fs::write(model.join("cameras.txt"), cameras).expect("write");
    std::fs::write(model.join("images.txt"), images).expect("write");
    std::fs::write(model.join("points3D.txt"), pts).expect("write");
    write_images(&dir.join("images"), cams);
}

/// Little-endian byte writer for COLMAP binary models.
#[derive(Default)]
pub struct Le(pub Vec<u8>);

impl Le {
    pub fn u32(&mut self, v: u32) -> &mut Self {
        self.0.extend(v.to_le_bytes());
        self
    }
    pub fn i32(&mut self, v: i32) -> &mut Self {
        self.0.extend(v.to_le_bytes());
        self
    }
    pub fn u64(&mut self, v: u64) -> &mut Self {
        self.0.extend(v.to_le_bytes());
        self
    }
    pub fn f64(&mut self, v: f64) -> &mut Self {
        self.0.extend(v.to_le_bytes());
        self
    }
    pub fn bytes(&mut self, v: &[u8]) -> &mut Self {
        self.0.extend_from_slice(v);
        self
    }
}

/// Writes a COLMAP binary model to `dir/sparse/0/` plus `dir/images/` (same layout as
/// [`write_colmap_text`]).
pub fn write_colmap_bin(dir: &Path, cams: &[NamedCamera], models: &[&str], points: &[DVec3]) {
    let model = dir.join("sparse/0");
    std::fs::create_dir_all(&model).expect("mkdir");
    let mut cb = Le::default();
    let mut ib = Le::default();
    cb.u64(cams.len() as u64);
    ib.u64(cams.len() as u64);
    for (i, c) in cams.iter().enumerate() {
        let m = models[i % models.len()];
        let id = COLMAP_MODELS
            .iter()
            .find(|(n, _)| *n == m)
            .map(|(_, id)| *id)
            .expect("known model");
        let k = &c.camera.intrinsics;
        cb.u32(i as u32 + 1)
            .i32(id)
            .u64(k.width as u64)
            .u64(k.height as u64);
        for p in colmap_params(m, k) {
            cb.f64(p);
        }
        ib.u32(i as u32 + 1);
        for q in colmap_quat(c.camera.pose.rotation) {
            ib.f64(q);
        }
        let t = c.camera.pose.translation;
        ib.f64(t.x).f64(t.y).f64(t.z).u32(i as u32 + 1);
        ib.bytes(c.name.as_bytes()).bytes(&[0]);
        let npts = (i % 3) as u64;
        ib.u64(npts);
        for j in 0..npts {
            ib.f64(j as f64 + 0.5).f64(2.5).u64(u64::MAX);
        }
    }
    let mut pb = Le::default();
    pb.u64(points.len() as u64);
    for (i, p) in points.iter().enumerate() {
        pb.u64(i as u64 + 1).f64(p.x).f64(p.y).f64(p.z);
        pb.bytes(&[10, 20, 30]).f64(0.25).u64(2);
        pb.u32(1).u32(0).u32(2).u32(0);
    }
    std::fs::write(model.join("cameras.bin"), cb.0).expect("write");
    std::fs::write(model.join("images.bin"), ib.0).expect("write");
    std::fs::write(model.join("points3D.bin"), pb.0).expect("write");
    write_images(&dir.join("images"), cams);
}

/// The NeRF (OpenGL camera-to-world) `transform_matrix` of a pose.
pub fn gl_transform_matrix(pose: &WorldToCamera) -> Value {
    let c2w = pose.inverse();
    let r = c2w.rotation * DMat3::from_diagonal(DVec3::new(1.0, -1.0, -1.0));
    let c = c2w.translation;
    let row = |i: usize| json!([r.x_axis[i], r.y_axis[i], r.z_axis[i], c[i]]);
    json!([row(0), row(1), row(2), [0.0, 0.0, 0.0, 1.0]])
}

/// A `transforms.json` for `cams` with images in `images/`; intrinsics per frame, or at
/// the top level (from camera 0) when `shared`.
pub fn nerf_json(cams: &[NamedCamera], shared: bool, bounds: Option<(f64, f64)>) -> Value {
    let intr = |k: &Intrinsics| {
        let d = k.distortion.unwrap_or_default();
        json!({"fl_x": k.fx, "fl_y": k.fy, "cx": k.cx, "cy": k.cy, "w": k.width, "h": k.height,
               "k1": d.k1, "k2": d.k2, "p1": d.p1, "p2": d.p2})
    };
    let frames: Vec<Value> = cams
        .iter()
        .map(|c| {
            let mut f = json!({
                "file_path": format!("images/{}", c.name),
                "transform_matrix": gl_transform_matrix(&c.camera.pose),
            });
            if !shared {
                if let (Some(f), Some(k)) =
                    (f.as_object_mut(), intr(&c.camera.intrinsics).as_object())
                {
                    f.extend(k.clone());
                }
            }
            f
        })
        .collect();
    let mut top = if shared {
        intr(&cams[0].camera.intrinsics)
    } else {
        json!({})
    };
    top["frames"] = Value::Array(frames);
    if let Some((n, f)) = bounds {
        top["near"] = json!(n);
        top["far"] = json!(f);
    }
    top
}

/// Writes a NeRF scene (`transforms.json` + `images/`).
pub fn write_nerf(dir: &Path, cams: &[NamedCamera], shared: bool, bounds: Option<(f64, f64)>) {
    let text = serde_json::to_string_pretty(&nerf_json(cams, shared, bounds)).expect("json");
    std::fs::create_dir_all(dir).expect("mkdir");
    std::fs::write(dir.join("transforms.json"), text).expect("write");
    write_images(&dir.join("images"), cams);
}

/// The `*_par.txt` line of a camera: `name K R t`, row-major.
pub fn middlebury_line(c: &NamedCamera) -> String {
    let k = &c.camera.intrinsics;
    let r = c.camera.pose.rotation;
    let t = c.camera.pose.translation;
    let mut v = vec![k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0];
    for i in 0..3 {
        v.extend([r.x_axis[i], r.y_axis[i], r.z_axis[i]]);
    }
    v.extend([t.x, t.y, t.z]);
    let nums: Vec<String> = v.iter().map(|x| x.to_string()).collect();
    format!("{} {}", c.name, nums.join(" "))
}

/// Writes a Middlebury scene: `scene_par.txt` and the images beside it.
pub fn write_middlebury(dir: &Path, cams: &[NamedCamera]) {
    let mut text = format!("{}\n", cams.len());
    for c in cams {
        text += &middlebury_line(c);
        text.push('\n');
    }
    std::fs::create_dir_all(dir).expect("mkdir");
    std::fs::write(dir.join("scene_par.txt"), text).expect("write");
    write_images(dir, cams);
}

/// Largest absolute difference between two 3x3 matrices.
pub fn mat_diff(a: DMat3, b: DMat3) -> f64 {
    (a - b)
        .to_cols_array()
        .iter()
        .fold(0.0f64, |m, v| m.max(v.abs()))
}

/// Asserts two cameras agree: intrinsics (and distortion) within `tol` relative to the
/// focal length, rotation and translation within `tol` (absolute).
pub fn assert_same_camera(what: &str, got: &Camera, want: &Camera, tol: f64) {
    let (g, w) = (&got.intrinsics, &want.intrinsics);
    assert_eq!((g.width, g.height), (w.width, w.height), "{what}: size");
    let scale = w.fx.abs().max(1.0);
    for (name, a, b) in [
        ("fx", g.fx, w.fx),
        ("fy", g.fy, w.fy),
        ("cx", g.cx, w.cx),
        ("cy", g.cy, w.cy),
    ] {
        assert!((a - b).abs() <= tol * scale, "{what}: {name} {a} vs {b}");
    }
    let (gd, wd) = (
        g.distortion.unwrap_or_default(),
        w.distortion.unwrap_or_default(),
    );
    for (a, b) in [
        (gd.k1, wd.k1),
        (gd.k2, wd.k2),
        (gd.p1, wd.p1),
        (gd.p2, wd.p2),
    ] {
        assert!((a - b).abs() <= tol, "{what}: distortion {gd:?} vs {wd:?}");
    }
    let dr = mat_diff(got.pose.rotation, want.pose.rotation);
    assert!(dr <= tol, "{what}: |R - R'| = {dr:e}");
    let dt = (got.pose.translation - want.pose.translation)
        .abs()
        .max_element();
    assert!(dt <= tol, "{what}: |t - t'| = {dt:e}");
}

/// One tensor of a safetensors file.
#[derive(Debug)]
pub struct Tensor {
    pub dtype: String,
    pub shape: Vec<usize>,
    pub bytes: Vec<u8>,
}

impl Tensor {
    pub fn f32s(&self) -> Vec<f32> {
        assert_eq!(self.dtype, "F32");
        self.bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    }
    pub fn i64s(&self) -> Vec<i64> {
        assert_eq!(self.dtype, "I64");
        self.bytes
            .chunks_exact(8)
            .map(|c| i64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
            .collect()
    }
}

/// Reads every tensor of a safetensors file (8-byte header length, JSON header, data).
pub fn read_safetensors(path: &Path) -> BTreeMap<String, Tensor> {
    let bytes = std::fs::read(path).expect("read safetensors");
    let n = u64::from_le_bytes(bytes[..8].try_into().expect("8 bytes")) as usize;
    let header: Value = serde_json::from_slice(&bytes[8..8 + n]).expect("header JSON");
    let data = &bytes[8 + n..];
    let mut out = BTreeMap::new();
    for (name, info) in header.as_object().expect("object") {
        if name == "__metadata__" {
            continue;
        }
        let offs: Vec<usize> = info["data_offsets"]
            .as_array()
            .expect("offsets")
            .iter()
            .map(|v| v.as_u64().expect("offset") as usize)
            .collect();
        out.insert(
            name.clone(),
            Tensor {
                dtype: info["dtype"].as_str().expect("dtype").to_string(),
                shape: info["shape"]
                    .as_array()
                    .expect("shape")
                    .iter()
                    .map(|v| v.as_u64().expect("dim") as usize)
                    .collect(),
                bytes: data[offs[0]..offs[1]].to_vec(),
            },
        );
    }
    out
}

/// CRC-32 (IEEE) as PNG chunks use it.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// One PNG chunk: length, type, data, CRC.
fn png_chunk(out: &mut Vec<u8>, kind: &[u8; 4], data: &[u8]) {
    out.extend((data.len() as u32).to_be_bytes());
    let mut body = kind.to_vec();
    body.extend_from_slice(data);
    out.extend(&body);
    out.extend(crc32(&body).to_be_bytes());
}

/// A PNG whose header (signature, IHDR claiming `w x h` RGB8, start of IDAT) is valid but
/// whose pixel data is not: its size can be read, its pixels cannot be decoded.
pub fn png_without_pixels(w: u32, h: u32) -> Vec<u8> {
    let mut ihdr = Vec::new();
    ihdr.extend(w.to_be_bytes());
    ihdr.extend(h.to_be_bytes());
    ihdr.extend([8, 2, 0, 0, 0]);
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    png_chunk(&mut out, b"IHDR", &ihdr);
    png_chunk(&mut out, b"IDAT", &[0x78, 0x9c, 0xff, 0xff]);
    png_chunk(&mut out, b"IEND", &[]);
    out
}

/// `a` equals `b` to within JSON's float parsing (serde_json may be off by an ulp).
fn close(a: Option<f64>, b: f64) -> bool {
    a.is_some_and(|a| (a - b).abs() <= 1e-12 * b.abs().max(1.0))
}

/// `far` of `inspect --json`'s output as a reader takes it: a number, or infinity for
/// `null` (and for the string `"inf"` of files written before); `None` for anything else.
pub fn inspect_far(far: &Value) -> Option<f64> {
    match far {
        Value::Null => Some(f64::INFINITY),
        Value::String(s) if s == "inf" => Some(f64::INFINITY),
        v => v.as_f64(),
    }
}

/// The keys the issue lists, with the values the library reads; extra keys are only
/// `bounds_source` and per-view `distortion`.
pub fn check_inspect_json(json: &Value, scene: &deepstereo_core::scene::Scene, format: &str) {
    let top = json.as_object().expect("object");
    for key in ["format", "near", "far", "views"] {
        assert!(top.contains_key(key), "missing top-level key {key}");
    }
    for key in top.keys() {
        assert!(
            ["format", "near", "far", "views", "bounds_source"].contains(&key.as_str()),
            "unexpected top-level key {key}"
        );
    }
    assert_eq!(json["format"], format);
    assert!(close(json["near"].as_f64(), scene.near), "near");
    if scene.far.is_finite() {
        assert!(close(json["far"].as_f64(), scene.far), "far");
    } else {
        // JSON has no infinity: inspect writes null, and readers take it as infinity.
        assert!(json["far"].is_null(), "infinite far as {}", json["far"]);
        assert_eq!(inspect_far(&json["far"]), Some(f64::INFINITY));
    }
    let views = json["views"].as_array().expect("views");
    assert_eq!(views.len(), scene.views.len());
    const KEYS: [&str; 9] = ["name", "width", "height", "fx", "fy", "cx", "cy", "R", "t"];
    for (j, v) in views.iter().zip(&scene.views) {
        let o = j.as_object().expect("view object");
        for key in KEYS {
            assert!(o.contains_key(key), "view missing key {key}");
        }
        for key in o.keys() {
            assert!(
                KEYS.contains(&key.as_str()) || key == "distortion",
                "unexpected view key {key}"
            );
        }
        let k = &v.camera.intrinsics;
        assert_eq!(j["name"], v.name.as_str());
        assert_eq!(j["width"].as_u64(), Some(k.width as u64));
        assert_eq!(j["height"].as_u64(), Some(k.height as u64));
        for (key, val) in [("fx", k.fx), ("fy", k.fy), ("cx", k.cx), ("cy", k.cy)] {
            assert!(close(j[key].as_f64(), val), "{key}");
        }
        let r: Vec<f64> = j["R"]
            .as_array()
            .expect("R")
            .iter()
            .map(|x| x.as_f64().expect("number"))
            .collect();
        assert_eq!(r.len(), 9, "R is 3x3 row-major");
        let rot = v.camera.pose.rotation;
        let want = DMat3::from_cols_array(&[r[0], r[3], r[6], r[1], r[4], r[7], r[2], r[5], r[8]]);
        assert!(
            mat_diff(rot, want) < 1e-12,
            "{format} {}: R row-major: {rot:?} vs {want:?}",
            v.name
        );
        let t: Vec<f64> = j["t"]
            .as_array()
            .expect("t")
            .iter()
            .map(|x| x.as_f64().expect("number"))
            .collect();
        assert_eq!(t.len(), 3);
        for (a, b) in t.iter().zip(v.camera.pose.translation.to_array()) {
            assert!(close(Some(*a), b), "t: {t:?}");
        }
    }
}

/// A Chromium binary that runs, if any.
pub fn chromium() -> Option<&'static str> {
    ["chromium", "chromium-browser", "google-chrome"]
        .into_iter()
        .find(|p| {
            std::process::Command::new(p)
                .arg("--version")
                .output()
                .map(|o| o.status.success())
                .unwrap_or(false)
        })
}

/// Whether the environment variable `var` is `1` (tests/run-all.sh sets the
/// `DEEPSTEREO_REQUIRE_*` ones for tools it installed, whose tests then fail instead of
/// skipping).
pub fn required(var: &str) -> bool {
    std::env::var(var).is_ok_and(|v| v == "1")
}

/// Decodes standard base64 (RFC 4648; padding optional), or None if it is not.
pub fn base64_decode(text: &str) -> Option<Vec<u8>> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => Some(c - b'A'),
        b'a'..=b'z' => Some(c - b'a' + 26),
        b'0'..=b'9' => Some(c - b'0' + 52),
        b'+' => Some(62),
        b'/' => Some(63),
        _ => None,
    };
    let bytes: Vec<u8> = text.bytes().filter(|&c| c != b'=').collect();
    let mut out = Vec::with_capacity(bytes.len() * 3 / 4);
    for chunk in bytes.chunks(4) {
        let mut n = 0u32;
        for (i, &c) in chunk.iter().enumerate() {
            n |= (val(c)? as u32) << (18 - 6 * i);
        }
        out.extend_from_slice(&n.to_be_bytes()[1..chunk.len()]);
    }
    Some(out)
}

/// One procedural scene of `views` views at `w` x `h` (no supersampling) from `seed`,
/// written by `deepstereo synth` into `dir/scenes` with the extra options `extra`; its
/// directory.
pub fn synth_scene(
    dir: &Path,
    (w, h): (usize, usize),
    views: usize,
    seed: u64,
    extra: &[&str],
) -> PathBuf {
    let out = dir.join("scenes").to_string_lossy().into_owned();
    let (views, seed, size) = (views.to_string(), seed.to_string(), format!("{w}x{h}"));
    let mut args = vec![
        "synth",
        "--out",
        &out,
        "--scenes",
        "1",
        "--views",
        &views,
        "--seed",
        &seed,
        "--size",
        &size,
        "--supersample",
        "1",
    ];
    args.extend_from_slice(extra);
    let res = run_deepstereo(args);
    assert_eq!(res.code, Some(0), "synth failed: {}", res.stderr);
    dir.join("scenes/scene_0000")
}
