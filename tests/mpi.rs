//! `deepstereo mpi` end to end on a small generated scene: an MPI composited at its
//! reference camera is the network's render there (`render --pose`, >= 40 dB); the
//! viewer in headless Chromium shows it pixel for pixel at `?fit=native` (>= 30 dB; the
//! default margin of 64 pixels around the view left out), and
//! moved (`?offset=`) as `render --mpi` does on the CPU; rays an MPI does not cover are
//! filled alike on the CPU and in the viewer; an MPI's planes lie over the depths its
//! reference camera sees (`--plane-span view`); several MPIs render a path and
//! a video, and the viewer blends them as `render --mpi` does; bad input is refused with
//! nothing written.

use deepstereo_core::imageio::RgbImage;
use deepstereo_core::metrics::psnr;
use deepstereo_core::mpi::{io, viewer, Mpi};
use deepstereo_tests::*;
use std::path::{Path, PathBuf};
use std::process::Command;

const W: u32 = 64;
const H: u32 = 48;

/// The model options of the MPIs the tests bake and of the renders they are checked against.
const COMMON: [&str; 8] = [
    "--planes", "8", "--prune", "off", "--tile", "32", "--views", "4",
];

fn scene(dir: &Path) -> PathBuf {
    synth_scene(dir, (W as usize, H as usize), 6, 11, &["--rig", "forward"])
}

fn load(path: &Path) -> RgbImage {
    RgbImage::load(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The `image.png` a `render` command line (`args`, without `--out`) writes into `out`.
fn image(args: &[&str], out: &str) -> RgbImage {
    let mut a = args.to_vec();
    a.extend(["--out", out]);
    ok(&a);
    load(&Path::new(out).join("image.png"))
}

/// `mpi --target 2` of the scene `s` into `out`, with `extra` options and the model
/// options [`COMMON`].
fn bake_view_2(s: &str, out: &str, extra: &[&str]) {
    let mut args = vec!["mpi", "--scene", s, "--target", "2", "--out", out];
    args.extend(extra);
    args.extend(COMMON);
    ok(&args);
}

/// `render --mpi mpi` at the camera `scene_pose` names (the scene and `--pose` options),
/// in `dir`, against the network's `render` with the options `common` (which hold them)
/// and `with`, and with `common` alone: the MPI is the first (>= 40 dB) and not the
/// second (at least 3 dB further). Returns both PSNRs.
fn mpi_is_render_with(
    dir: &Path,
    scene_pose: &[&str],
    mpi: &str,
    common: &[&str],
    with: &[&str],
) -> (f64, f64) {
    let t = |p: &str| dir.join(p).to_string_lossy().into_owned();
    let via = image(
        &[&["render"][..], scene_pose, &["--mpi", mpi]].concat(),
        &t("via"),
    );
    let net = image(&[&["render"][..], with, common].concat(), &t("net_with"));
    let plain = image(&[&["render"][..], common].concat(), &t("net_without"));
    let (db, db_plain) = (psnr(&via, &net), psnr(&via, &plain));
    assert!(db >= 40.0, "MPI vs render {with:?}: {db:.1} dB");
    assert!(
        db_plain < db - 3.0,
        "MPI vs render without {with:?}: {db_plain:.1} dB, with them {db:.1}"
    );
    (db, db_plain)
}

/// View `view` of `inspect --json` as a camera file, changed by `edit`.
fn edited_pose(
    scene: &Path,
    view: usize,
    out: &Path,
    edit: impl FnOnce(&mut serde_json::Value),
) -> PathBuf {
    let res = ok(&["inspect", "--scene", &scene.to_string_lossy(), "--json"]);
    let all: serde_json::Value = serde_json::from_str(&res.stdout).expect("inspect JSON");
    let mut cam = all["views"][view].clone();
    edit(&mut cam);
    std::fs::write(out, cam.to_string()).expect("write pose");
    out.to_path_buf()
}

/// View `view` of `inspect --json` as a camera file, its centre moved by `offset` in its
/// own axes (`t' = t - offset`).
fn pose_file(scene: &Path, view: usize, offset: [f64; 3], out: &Path) -> PathBuf {
    edited_pose(scene, view, out, |cam| {
        for (i, o) in offset.iter().enumerate() {
            let t = cam["t"][i].as_f64().expect("t");
            cam["t"][i] = serde_json::json!(t - o);
        }
    })
}

/// The first frame of `page` (a file URL with its query; `capture=1` is added) in
/// headless Chromium with software WebGL, as the page's own `canvas.toDataURL` PNG read
/// back through `--dump-dom`; None when no Chromium runs and none is required.
fn screenshot(page: &str, dir: &Path, name: &str) -> Option<RgbImage> {
    let dom = dump_dom(page, dir, name, (W, H))?;
    let key = "data-capture=\"data:image/png;base64,";
    let at = dom.find(key).expect("a capture");
    let b64 = dom[at + key.len()..].split('"').next().unwrap_or_default();
    let png = base64_decode(b64).expect("base64 PNG");
    let path = dir.join(format!("{name}.png"));
    std::fs::write(&path, png).expect("write capture");
    let img = load(&path);
    assert_eq!((img.width, img.height), (W, H), "the canvas at ?fit=native");
    Some(img)
}

/// The DOM of `page` (`capture=1` added) after its first frame, in headless Chromium with
/// software WebGL and a `window` (width, height) window; None when no Chromium runs and
/// none is required.
fn dump_dom(page: &str, dir: &Path, name: &str, window: (u32, u32)) -> Option<String> {
    let Some(browser) = chromium() else {
        assert!(
            !required("DEEPSTEREO_REQUIRE_CHROMIUM"),
            "Chromium is required (DEEPSTEREO_REQUIRE_CHROMIUM=1) but does not run"
        );
        eprintln!(
            "SKIPPED the viewer check: no chromium on the PATH (tests/run-all.sh installs it)"
        );
        return None;
    };
    // A headless browser now and then ends before the page is ready on a loaded machine:
    // one more try, with a profile of its own, before the check fails.
    let key = "data-capture=\"data:image/png;base64,";
    let mut dom = String::new();
    for attempt in 0..2 {
        let res = Command::new(browser)
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-dev-shm-usage",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--force-device-scale-factor=1",
                "--virtual-time-budget=20000",
                "--dump-dom",
            ])
            .arg(format!(
                "--user-data-dir={}",
                dir.join(format!("profile-{name}-{attempt}")).display()
            ))
            .arg(format!("--window-size={},{}", window.0, window.1))
            .arg(format!("{page}&capture=1"))
            .output()
            .expect("run chromium");
        dom = String::from_utf8_lossy(&res.stdout).into_owned();
        if dom.contains(key) {
            break;
        }
        let why = format!(
            "{browser}: no capture in the page:\n{}\n{}",
            dom.chars().take(600).collect::<String>(),
            String::from_utf8_lossy(&res.stderr)
        );
        assert!(attempt == 0, "{why}");
        eprintln!("trying again: {why}");
    }
    Some(dom)
}

/// The viewer in a window of another aspect than its MPI's fills it at the MPI's aspect,
/// centred (letterboxed), not drawn into a corner.
fn check_letterbox(url: &str, dir: &Path, mpi_aspect: f64) {
    for (name, window) in [("wide", (800, 300)), ("tall", (520, 900))] {
        let Some(dom) = dump_dom(url, dir, name, window) else {
            return;
        };
        let key = "data-fit=\"";
        let at = dom.find(key).expect("data-fit");
        let fit: Vec<f64> = dom[at + key.len()..]
            .split('"')
            .next()
            .unwrap_or_default()
            .split(',')
            .filter_map(|v| v.parse().ok())
            .collect();
        let [left, top, w, h, ww, wh] = fit[..] else {
            panic!("data-fit: {fit:?}");
        };
        let fills = (w - ww).abs() <= 1.0 || (h - wh).abs() <= 1.0;
        assert!(fills && w <= ww + 1.0 && h <= wh + 1.0, "{name}: {fit:?}");
        assert!(
            (w / h - mpi_aspect).abs() < 0.05 * mpi_aspect,
            "{name}: aspect {fit:?}"
        );
        assert!(
            (left - (ww - w) / 2.0).abs() <= 1.0,
            "{name}: not centred {fit:?}"
        );
        assert!(
            (top - (wh - h) / 2.0).abs() <= 1.0,
            "{name}: not centred {fit:?}"
        );
    }
}

/// At view 2's camera of the scene `s` in `dir`: the network's render (`render --pose`
/// with the model options `common`) and the render of the MPI in `mpi` (`render --mpi`),
/// in `dir/net` and `dir/via`.
fn at_reference(dir: &Path, s: &str, mpi: &str, common: &[&str]) -> (RgbImage, RgbImage) {
    let pose = pose_file(
        dir.join("scenes/scene_0000").as_path(),
        2,
        [0.0; 3],
        &dir.join("pose.json"),
    );
    let pose = pose.to_string_lossy().into_owned();
    let t = |p: &str| dir.join(p).to_string_lossy().into_owned();
    let (net, via) = (t("net"), t("via"));
    let mut args = vec!["render", "--scene", s, "--pose", &pose, "--out", &net];
    args.extend(common);
    ok(&args);
    ok(&[
        "render", "--scene", s, "--mpi", mpi, "--pose", &pose, "--out", &via,
    ]);
    (
        load(&dir.join("net/image.png")),
        load(&dir.join("via/image.png")),
    )
}

/// At view `view`'s camera of the scene `s` in `dir`, moved by `off` in its own axes:
/// `render --mpi` of the MPIs in the directory `mpi` (into `dir/NAME_cpu`), and the
/// first frame of the viewer beside them opened there (`index.html?fit=native&offset=`;
/// None when no Chromium runs and none is required).
fn moved(
    dir: &Path,
    s: &str,
    mpi: &str,
    view: usize,
    off: [f64; 3],
    name: &str,
) -> (RgbImage, Option<RgbImage>) {
    let json = dir.join(format!("{name}.json"));
    let pose = pose_file(dir.join("scenes/scene_0000").as_path(), view, off, &json);
    let out = dir.join(format!("{name}_cpu"));
    ok(&[
        "render",
        "--scene",
        s,
        "--mpi",
        mpi,
        "--pose",
        &pose.to_string_lossy(),
        "--out",
        &out.to_string_lossy(),
    ]);
    let cpu = load(&out.join("image.png"));
    let [x, y, z] = off;
    let page = format!("file://{mpi}/index.html?fit=native&offset={x},{y},{z}");
    (cpu, screenshot(&page, dir, name))
}

#[test]
fn an_mpi_at_its_reference_is_the_networks_render_and_the_viewer_shows_it() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let s = s.to_string_lossy().into_owned();
    let t = |p: &str| tmp.path().join(p).to_string_lossy().into_owned();
    let common = COMMON;
    let m = t("mpi");
    bake_view_2(&s, &m, &[]);
    for f in [
        "mpi.json",
        "plane_00.png",
        "plane_07.png",
        "index.html",
        "mpi.js",
    ] {
        assert!(tmp.path().join("mpi").join(f).is_file(), "{f} missing");
    }
    let js = std::fs::read_to_string(tmp.path().join("mpi/mpi.js")).expect("mpi.js");
    assert!(js.contains("data:image/png;base64,") && !js.contains("http"));

    let (net_img, via_img) = at_reference(tmp.path(), &s, &m, &common);
    let db = psnr(&via_img, &net_img);
    assert!(
        db >= 40.0,
        "MPI at its reference vs render --pose: {db:.1} dB"
    );

    let url = format!("file://{}/mpi/index.html", tmp.path().display());
    let Some(shot) = screenshot(&format!("{url}?fit=native"), tmp.path(), "native") else {
        return;
    };
    let db = psnr(&shot, &via_img);
    assert!(
        db >= 30.0,
        "viewer at ?fit=native vs the MPI's composite: {db:.1} dB"
    );
    check_letterbox(&format!("{url}?"), tmp.path(), W as f64 / H as f64);
    eprintln!("viewer at the reference: {db:.1} dB");

    // Moved along the camera's x and z axes: the viewer and the CPU agree.
    let (cpu, shot) = moved(tmp.path(), &s, &m, 2, [0.08, -0.03, 0.05], "moved");
    let shot = shot.expect("chromium ran before");
    let db = psnr(&shot, &cpu);
    assert!(db >= 30.0, "viewer moved vs render --mpi: {db:.1} dB");
    assert!(psnr(&cpu, &via_img) < db, "the move changed nothing");
    eprintln!("viewer moved: {db:.1} dB");
}

/// An MPI without a margin, seen from a camera turned beyond its image: the rays it does
/// not cover are filled from those around them (no black pixel), the same on the CPU and
/// in the viewer.
#[test]
fn rays_no_mpi_covers_are_filled_alike_on_the_cpu_and_in_the_viewer() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let s = s.to_string_lossy().into_owned();
    let t = |p: &str| tmp.path().join(p).to_string_lossy().into_owned();
    let m0 = t("mpi0");
    bake_view_2(&s, &m0, &["--margin", "0"]);
    let (yaw, pitch) = (0.3, -0.1);
    let mpi0 = io::read_dir(Path::new(&m0))
        .expect("read the MPI")
        .remove(0);
    let mut cam = mpi0.camera;
    let centre = cam.pose.centre();
    cam.pose.rotation =
        glam::DMat3::from_rotation_x(pitch) * glam::DMat3::from_rotation_y(yaw) * cam.pose.rotation;
    cam.pose.translation = -(cam.pose.rotation * centre);
    let (_, alpha) = mpi0.render(&cam);
    let holes = alpha.iter().filter(|&&a| a <= 0.0).count();
    assert!(
        holes > alpha.len() / 20,
        "only {holes} pixels uncovered: turn farther"
    );
    let scene0 = tmp.path().join("scenes/scene_0000");
    let pose = edited_pose(&scene0, 2, &tmp.path().join("turned.json"), |json| {
        json["R"] = serde_json::json!(cam.pose.rotation.transpose().to_cols_array());
        json["t"] = serde_json::json!(cam.pose.translation.to_array());
    });
    let cpu = image(
        &[
            "render",
            "--scene",
            &s,
            "--mpi",
            &m0,
            "--pose",
            &pose.to_string_lossy(),
        ],
        &t("turned_cpu"),
    );
    let dark = (cpu.data.chunks(3))
        .filter(|p| p.iter().all(|&v| v < 1.0 / 255.0))
        .count();
    assert_eq!(dark, 0, "{dark} black pixels where {holes} were uncovered");
    let page = format!("file://{m0}/index.html?fit=native&look={yaw},{pitch}");
    let Some(shot) = screenshot(&page, tmp.path(), "turned") else {
        return;
    };
    let db = psnr(&shot, &cpu);
    assert!(
        db >= 30.0,
        "viewer beyond the MPI vs render --mpi: {db:.1} dB"
    );
    eprintln!(
        "viewer turned beyond the MPI ({holes} of {} pixels filled): {db:.1} dB",
        alpha.len()
    );
}

#[test]
fn several_mpis_render_a_path_and_bad_input_is_refused() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path()).to_string_lossy().into_owned();
    let t = |p: &str| tmp.path().join(p).to_string_lossy().into_owned();
    let m = t("mpis");
    ok(&[
        "mpi",
        "--scene",
        &s,
        "--targets",
        "1,3",
        "--holdout",
        "0",
        "--planes",
        "6",
        "--margin",
        "8",
        "--tile",
        "32",
        "--out",
        &m,
    ]);
    for f in [
        "mpi_00/mpi.json",
        "mpi_01/plane_05.png",
        "index.html",
        "mpi.js",
    ] {
        assert!(tmp.path().join("mpis").join(f).is_file(), "{f} missing");
    }
    let frames = t("frames");
    ok(&[
        "render",
        "--scene",
        &s,
        "--mpi",
        &m,
        "--path",
        "spiral",
        "--frames",
        "3",
        "--out",
        &frames,
        "--video",
        &t("path.gif"),
    ]);
    for f in 0..3 {
        let img = load(&tmp.path().join(format!("frames/frame_{f:04}.png")));
        assert_eq!((img.width, img.height), (W, H));
        assert!(img.data.iter().all(|v| v.is_finite()));
    }
    assert!(tmp.path().join("path.gif").is_file());

    // The viewer blends two MPIs, each margin weighed down against the MPIs' own views,
    // as `render --mpi` does. Recoloured red and blue (alphas kept), so that every
    // pixel shows the blend's weights; the view is moved so that it sees part of the
    // first MPI's margin.
    let dir = tmp.path().join("mpis");
    for (name, rgb) in [("mpi_00", [1.0, 0.0, 0.0]), ("mpi_01", [0.0, 0.0, 1.0])] {
        let baked = io::read(&dir.join(name)).expect("read the MPI");
        let planes = (baked.planes().iter())
            .map(|p| {
                (p.chunks(4))
                    .flat_map(|t| [rgb[0], rgb[1], rgb[2], t[3]])
                    .collect()
            })
            .collect();
        let mut mpi = Mpi::new(baked.camera, baked.inv_depths.clone(), planes).expect("MPI");
        mpi.margin = baked.margin;
        io::write(&mpi, &dir.join(name)).expect("write the MPI");
    }
    viewer::write(&dir, &["mpi_00", "mpi_01"], 1.0).expect("write the viewer");
    if let (cpu, Some(shot)) = moved(tmp.path(), &s, &m, 1, [0.3, 0.0, 0.0], "blend") {
        let db = psnr(&shot, &cpu);
        eprintln!("viewer, two MPIs, moved: {db:.1} dB");
        // Flat colours: the viewer's 8-bit layers agree with the CPU to about 50 dB here;
        // a blend that takes the first MPI's margin as its view scores about 27.
        assert!(
            db >= 40.0,
            "viewer blending two MPIs vs render --mpi: {db:.1} dB"
        );
    }

    // Bad input: a clear error naming the problem, and nothing written.
    let bad = |args: &[&str], want: &str| {
        let res = run_deepstereo(args);
        assert!(res.code.is_some_and(|c| c != 0), "{args:?} should fail");
        assert!(
            res.stderr.contains(want),
            "{args:?}: want '{want}' in:\n{}",
            res.stderr
        );
        assert!(!tmp.path().join("bad").exists(), "{args:?} wrote output");
    };
    let out = t("bad");
    bad(
        &[
            "mpi",
            "--scene",
            &s,
            "--target",
            "0",
            "--holdout",
            "0",
            "--out",
            &out,
        ],
        "held out",
    );
    bad(
        &["mpi", "--scene", &s, "--target", "9", "--out", &out],
        "out of range",
    );
    bad(
        &["mpi", "--scene", &s, "--targets", "1,1", "--out", &out],
        "twice",
    );
    bad(
        &[
            "mpi", "--scene", &s, "--target", "1", "--margin", "100000", "--out", &out,
        ],
        "--margin 100000",
    );
    for tau in ["--agree=-0.1", "--agree=nan", "--agree=inf"] {
        bad(
            &["mpi", "--scene", &s, "--target", "1", tau, "--out", &out],
            "positive colour scale",
        );
    }
    // Planes beyond any memory: an error, not an abort, from the bake and the render.
    for cmd in ["mpi", "render"] {
        bad(
            &[
                cmd,
                "--scene",
                &s,
                "--target",
                "1",
                "--planes",
                "100000000",
                "--prune",
                "off",
                "--out",
                &out,
            ],
            "cannot be allocated",
        );
    }
    bad(
        &["mpi", "--scene", &s, "--eval", "--out", &out],
        "held-out views",
    );
    bad(
        &[
            "render", "--scene", &s, "--mpi", &s, "--target", "1", "--out", &out,
        ],
        "mpi.json",
    );
    std::fs::write(tmp.path().join("mpis/mpi_01/plane_02.png"), b"not a png").expect("write");
    bad(
        &[
            "render", "--scene", &s, "--mpi", &m, "--target", "1", "--out", &out,
        ],
        "plane_02.png",
    );
    let json = tmp.path().join("mpis/mpi_00/mpi.json");
    let text = std::fs::read_to_string(&json)
        .expect("read")
        .replace("\"fx\": ", "\"fx\": -");
    std::fs::write(&json, text).expect("write");
    bad(
        &[
            "render", "--scene", &s, "--mpi", &m, "--target", "1", "--out", &out,
        ],
        "mpi.json",
    );
}

/// `--margin M` bakes a larger image around the reference: `mpi.json` is `2M` pixels wider
/// and taller with the principal point moved by `M`, and at the reference camera the MPI
/// still renders as the network does there (the network fills the margin from the
/// sources; it is translation-equivariant when `M` is a multiple of its alignment).
#[test]
fn an_mpi_with_a_margin_is_larger_and_still_exact_at_its_reference() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let s = s.to_string_lossy().into_owned();
    let t = |p: &str| tmp.path().join(p).to_string_lossy().into_owned();
    let common = COMMON;
    let m = t("mpi");
    bake_view_2(&s, &m, &["--margin", "8"]);
    let desc: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(tmp.path().join("mpi/mpi.json")).expect("mpi.json"),
    )
    .expect("mpi.json is JSON");
    assert_eq!(
        (
            desc["width"].as_u64(),
            desc["height"].as_u64(),
            desc["margin"].as_u64()
        ),
        (Some(W as u64 + 16), Some(H as u64 + 16), Some(8))
    );
    let (net_img, via_img) = at_reference(tmp.path(), &s, &m, &common);
    let db = psnr(&via_img, &net_img);
    assert!(
        db >= 40.0,
        "MPI with a margin at its reference vs render --pose: {db:.1} dB"
    );
}

/// With pruning on (the default), the MPI holds the pruned render's layers: at a camera
/// between the views (`mpi --pose`), its composite equals `render --pose` there with the
/// same options (>= 40 dB), where pruning (a coarse pass keeping half the selection, no
/// margin) visibly changes that render, and the planes the coarse pass leaves out of a
/// block have alpha 0 where the unpruned bake (`--prune off`) gives them some.
#[test]
fn a_pruned_mpi_is_the_pruned_render_at_its_reference_and_empty_off_its_surfaces() {
    let tmp = tempfile::tempdir().expect("tempdir");
    // Larger than `scene`'s views, so the coarse pass has blocks to leave planes out of.
    let s = synth_scene(tmp.path(), (128, 96), 6, 11, &["--rig", "forward"]);
    let pose = pose_file(&s, 2, [0.05, 0.02, 0.0], &tmp.path().join("pose.json"));
    let (s, pose) = (s.to_string_lossy(), pose.to_string_lossy());
    let t = |p: &str| tmp.path().join(p).to_string_lossy().into_owned();
    // Thinning off, so both bakes have the same planes.
    let common = [
        "--scene",
        &s,
        "--pose",
        &pose,
        "--planes",
        "24",
        "--views",
        "4",
        "--prune-max-step",
        "0",
        "--prune-keep",
        "0.5",
        "--prune-margin",
        "0",
    ];
    let (m, off) = (t("mpi"), t("mpi_off"));
    for (out, prune) in [(&m, "auto"), (&off, "off")] {
        let mut args = vec!["mpi", "--margin", "0", "--prune", prune, "--out", out];
        args.extend(common);
        ok(&args);
    }
    let net = image(&[&["render"][..], &common].concat(), &t("net"));
    let via = image(
        &["render", "--scene", &s, "--pose", &pose, "--mpi", &m],
        &t("via"),
    );
    let via_off = image(
        &["render", "--scene", &s, "--pose", &pose, "--mpi", &off],
        &t("via_off"),
    );
    let (db, db_off) = (psnr(&via, &net), psnr(&via_off, &net));
    assert!(
        db >= 40.0,
        "pruned MPI at its reference vs render --pose: {db:.1} dB"
    );
    assert!(
        db_off < db - 3.0,
        "pruning changed the render by little: {db_off:.1} dB"
    );

    let (pruned, full) = (
        io::read(Path::new(&m)).expect("read the MPI"),
        io::read(Path::new(&off)).expect("read the MPI"),
    );
    assert_eq!(pruned.inv_depths, full.inv_depths);
    let texels = |mpi: &Mpi| -> Vec<f32> {
        mpi.planes()
            .iter()
            .flat_map(|p| p.chunks(4).map(|t| t[3]))
            .collect()
    };
    let (a, f) = (texels(&pruned), texels(&full));
    let emptied = a
        .iter()
        .zip(&f)
        .filter(|(a, f)| **a == 0.0 && **f > 0.01)
        .count();
    let filled = f.iter().filter(|f| **f > 0.01).count();
    assert!(
        emptied * 10 > filled,
        "pruning emptied {emptied} of the {filled} texels the full bake fills"
    );
    eprintln!(
        "pruning emptied {emptied} of the {filled} texels; at the reference {db:.1} dB, unpruned {db_off:.1} dB"
    );
}

/// Without --views, an MPI of the embedded model (any number of views) is baked from 8
/// sources, or as many as the scene offers: at a camera between the views of a 6-view
/// scene (`mpi --pose`), from all 6, so it is `render --pose --views 6` there, not the
/// 4-view render.
#[test]
fn an_mpi_is_baked_from_up_to_8_views_by_default() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path());
    let pose = pose_file(&s, 2, [0.05, 0.02, 0.0], &tmp.path().join("pose.json"));
    let (s, pose) = (s.to_string_lossy(), pose.to_string_lossy());
    let t = |p: &str| tmp.path().join(p).to_string_lossy().into_owned();
    let common = [
        "--scene", &s, "--pose", &pose, "--planes", "8", "--prune", "off",
    ];
    let m = t("mpi");
    ok(&[&["mpi", "--margin", "0", "--out", &m][..], &common].concat());
    let scene_pose = ["--scene", &s, "--pose", &pose];
    mpi_is_render_with(tmp.path(), &scene_pose, &m, &common, &["--views", "6"]);
}

/// A COLMAP text copy of the generated scene `synth` in `out` (the same cameras and
/// images) with 49 sparse points on a 7x7 grid of view `view`'s rays (the middle half of
/// its image, so that a camera beside it sees them too) at depths `z0` to `z1`; and the
/// generated scene's near and far.
fn colmap_with_points(synth: &Path, out: &Path, view: usize, (z0, z1): (f64, f64)) -> (f64, f64) {
    let loaded = deepstereo_core::scene::Scene::load(synth, &Default::default()).expect("scene");
    let cams: Vec<NamedCamera> = (loaded.views.iter())
        .map(|v| NamedCamera {
            name: v.name.clone(),
            camera: v.camera,
        })
        .collect();
    let c = loaded.views[view].camera;
    let to_world = c.pose.inverse();
    let points: Vec<glam::DVec3> = (0..49)
        .map(|i| {
            let uv = glam::DVec2::new(
                (0.25 + 0.5 * (i % 7) as f64 / 6.0) * W as f64,
                (0.25 + 0.5 * (i / 7) as f64 / 6.0) * H as f64,
            );
            let n = c.intrinsics.unproject_pixel(uv);
            let z = z0 + (z1 - z0) * i as f64 / 48.0;
            to_world.rotation * glam::DVec3::new(n.x * z, n.y * z, z) + to_world.translation
        })
        .collect();
    write_colmap_text(out, &cams, &["PINHOLE"], &points);
    for v in &loaded.views {
        std::fs::copy(&v.image_path, out.join("images").join(&v.name)).expect("copy image");
    }
    (loaded.near, loaded.far)
}

/// An MPI's planes lie over the depths its reference camera sees (`--plane-span view`,
/// the default of `mpi`): in a COLMAP copy of a generated scene whose sparse points lie
/// at depths 2.4-2.8 in front of view 2, read with the generated scene's wider near and
/// far, the 8 planes are evenly spaced in inverse depth over those points' range (widened
/// as pruning widens it), not over the scene's; its composite is `render --pose
/// --plane-span view` there (>= 40 dB), not the scene's planes' render; and
/// `--plane-span scene` bakes the scene's planes.
#[test]
fn an_mpi_spreads_its_planes_over_the_depths_its_view_sees() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let synth = scene(tmp.path());
    let colmap = tmp.path().join("colmap");
    let (near, far) = colmap_with_points(&synth, &colmap, 2, (2.4, 2.8));
    assert!(
        near < 2.0 && far > 4.0,
        "the generated scene spans {near}-{far}"
    );
    let pose = pose_file(&synth, 2, [0.05, 0.02, 0.0], &tmp.path().join("pose.json"));
    let (s, pose) = (colmap.to_string_lossy(), pose.to_string_lossy());
    let (n, f) = (near.to_string(), far.to_string());
    let t = |p: &str| tmp.path().join(p).to_string_lossy().into_owned();
    let scene_args = [
        "--scene", &s, "--format", "colmap", "--near", &n, "--far", &f, "--pose", &pose,
    ];
    let common = [&scene_args[..], &COMMON[..]].concat();
    let (m, m_scene) = (t("mpi"), t("mpi_scene"));
    ok(&[&["mpi", "--margin", "0", "--out", &m][..], &common].concat());
    let span = ["--plane-span", "scene"];
    ok(&[
        &["mpi", "--margin", "0", "--out", &m_scene][..],
        &common,
        &span,
    ]
    .concat());

    let inv = io::read(Path::new(&m)).expect("read the MPI").inv_depths;
    let whole = deepstereo_core::geometry::inverse_depths(near, far, 8);
    let read_scene = io::read(Path::new(&m_scene)).expect("read the MPI");
    assert!(read_scene
        .inv_depths
        .iter()
        .zip(&whole)
        .all(|(a, b)| (a - b).abs() < 1e-9));
    let step = (inv[0] - inv[7]) / 7.0;
    assert!(
        inv.windows(2).all(|w| ((w[0] - w[1]) - step).abs() < 1e-9),
        "{inv:?}"
    );
    // Within the scene's planes, around the points' 2.4-2.8 widened by 10%, at most the
    // scene grid's plane beyond each side, and less than half the scene's span.
    let grid = whole[0] - whole[1];
    let (lo, hi) = (1.0 / (2.8 * 1.1), 1.0 / (2.4 * 0.9));
    assert!(
        inv[0] <= whole[0] && inv[7] >= whole[7],
        "{inv:?} in {whole:?}"
    );
    assert!(
        inv[0] >= hi && inv[0] <= hi + grid + 1e-9,
        "{inv:?} in {whole:?}"
    );
    assert!(
        inv[7] <= lo && inv[7] >= lo - grid - 1e-9,
        "{inv:?} in {whole:?}"
    );
    assert!(
        inv[0] - inv[7] < 0.5 * (whole[0] - whole[7]),
        "{inv:?} in {whole:?}"
    );

    let scene_pose = ["--scene", &s, "--format", "colmap", "--pose", &pose];
    let view = ["--plane-span", "view"];
    let (db, db_scene) = mpi_is_render_with(tmp.path(), &scene_pose, &m, &common, &view);
    eprintln!(
        "planes {inv:?}; at the reference {db:.1} dB, against the scene's planes {db_scene:.1}"
    );
}

/// An MPI baked at a view with its own photograph shows, at that view,
/// what `render --pose` with the photograph among the sources shows (>= 40 dB), whichever
/// way the photograph enters: by default the planes are those of the bake without it
/// (`--exclude-own-photo`), reweighed by the photograph's agreement with the other views
/// (`--agree 0`: the same alphas, texel for texel), with their colours moved to that
/// picture; with `--own-photo-as-source` they are the network's layers with it.
#[test]
fn an_mpi_with_its_own_photograph_keeps_the_other_views_depths() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let s = scene(tmp.path()).to_string_lossy().into_owned();
    let t = |p: &str| tmp.path().join(p).to_string_lossy().into_owned();
    let (m, m0, m_src, m_ex) = (t("mpi"), t("mpi0"), t("mpi_src"), t("mpi_ex"));
    bake_view_2(&s, &m, &[]);
    bake_view_2(&s, &m0, &["--agree", "0"]);
    bake_view_2(&s, &m_src, &["--own-photo-as-source"]);
    bake_view_2(&s, &m_ex, &["--exclude-own-photo"]);
    for mpi in [&m, &m0, &m_src] {
        let (net, via) = at_reference(tmp.path(), &s, mpi, &COMMON);
        let db = psnr(&via, &net);
        assert!(
            db >= 40.0,
            "{mpi} at its reference vs render --pose: {db:.1} dB"
        );
    }
    let read = |d: &str| io::read(Path::new(d)).expect("read the MPI");
    let (own, unweighed, excluded) = (read(&m), read(&m0), read(&m_ex));
    let (mut moved, mut reweighed) = (0, 0);
    for ((a, b), c) in (unweighed.planes().iter())
        .zip(excluded.planes())
        .zip(own.planes())
    {
        for ((x, y), z) in a.chunks(4).zip(b.chunks(4)).zip(c.chunks(4)) {
            assert_eq!(x[3], y[3], "alphas differ");
            moved += usize::from((0..3).any(|c| (x[c] - y[c]).abs() > 1.5 / 255.0));
            reweighed += usize::from((z[3] - x[3]).abs() > 1.5 / 255.0);
        }
    }
    assert!(moved > 0, "no colour moved to the photograph's picture");
    assert!(reweighed > 0, "the photograph's agreement moved no alpha");
    assert!(moved > 0, "no colour moved to the photograph's picture");
}
