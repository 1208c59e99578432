use super::*;
use crate::camera::WorldToCamera;
use glam::DMat3;

fn camera(w: u32, h: u32, centre: DVec3) -> Camera {
    let k = Intrinsics::pinhole(40.0, 42.0, w as f64 / 2.0 + 0.3, h as f64 / 2.0 - 0.2, w, h);
    Camera::global(
        k,
        WorldToCamera {
            rotation: DMat3::IDENTITY,
            translation: -centre,
        },
    )
}

/// Deterministic values in [0, 1) (the warp's tests too).
pub(super) fn values(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 40) as f32 / (1u64 << 24) as f32
        })
        .collect()
}

/// Random layers: colours `[D, 3, H, W]` and a selection `[D, H, W]` summing to 1.
fn layers(d: usize, n: usize) -> (Vec<f32>, Vec<f32>) {
    let colours = values(d * 3 * n, 1);
    let mut sel = values(d * n, 2);
    for p in 0..n {
        let sum: f32 = (0..d).map(|z| sel[z * n + p]).sum();
        (0..d).for_each(|z| sel[z * n + p] /= sum);
    }
    (colours, sel)
}

#[test]
fn the_composite_at_the_reference_is_the_networks_sum() -> Result<()> {
    let (w, h, d) = (7, 5, 6);
    let n = w * h;
    let (colours, sel) = layers(d, n);
    let inv = crate::geometry::inverse_depths(1.0, f64::INFINITY, d);
    let mpi = Mpi::from_layers(camera(w as u32, h as u32, DVec3::ZERO), inv, &colours, &sel)?;
    let img = mpi.composite();
    let (rendered, alpha) = mpi.render(&mpi.camera);
    for p in 0..n {
        for c in 0..3 {
            let want: f32 = (0..d)
                .map(|z| sel[z * n + p] * colours[(z * 3 + c) * n + p])
                .sum();
            assert!(
                (img.data[p * 3 + c] - want).abs() < 1e-5,
                "composite at {p}"
            );
            assert!(
                (rendered.data[p * 3 + c] - want).abs() < OPAQUE_T + 1e-5,
                "render at {p} (rays stop once nearly opaque)"
            );
        }
        assert!((alpha[p] - 1.0).abs() < OPAQUE_T + 1e-5);
    }
    Ok(())
}

#[test]
fn rows_visit_by_bisection_exactly_as_ray_by_ray() -> Result<()> {
    // Planes with transparent holes seen from a camera turned and moved so that parts of
    // every plane fall outside the image, and some planes lie behind it.
    let (w, h, d) = (40, 30, 8);
    let (colours, mut sel) = layers(d, w * h);
    for (i, s) in sel.iter_mut().enumerate() {
        if (i / 7) % 3 == 0 {
            *s = 0.0;
        }
    }
    let inv = crate::geometry::inverse_depths(0.5, f64::INFINITY, d);
    let mut mpi = Mpi::from_layers(camera(w as u32, h as u32, DVec3::ZERO), inv, &colours, &sel)?;
    // A margin, so that the composite of the core (the view within it) differs.
    mpi.margin = 6;
    for (angle, centre) in [
        (0.0, DVec3::new(0.3, -0.2, 0.1)),
        (0.2, DVec3::new(-0.4, 0.3, -0.2)),
        (-0.5, DVec3::new(0.1, 0.1, 1.0)),
    ] {
        let mut cam = camera(w as u32, h as u32, centre);
        let turn = DMat3::from_rotation_y(angle) * DMat3::from_rotation_z(0.3 * angle);
        cam.pose = WorldToCamera {
            rotation: turn,
            translation: -(turn * centre),
        };
        let rel = cam.pose.relative_to(&mpi.camera.pose);
        let maps = mpi.plane_maps(rel.translation);
        let mut hits = 0;
        for y in 0..h {
            let rays: Vec<DVec3> = (0..w)
                .map(|x| {
                    let n = (cam.intrinsics)
                        .unproject_pixel(DVec2::new(x as f64 + 0.5, y as f64 + 0.5));
                    rel.rotation * DVec3::new(n.x, n.y, 1.0)
                })
                .collect();
            let (mut c1, mut a1, mut k1) = (vec![0f32; w * 3], vec![0f32; w], vec![0f32; w * 4]);
            let (mut c2, mut a2, mut k2) = (vec![0f32; w * 3], vec![0f32; w], vec![0f32; w * 4]);
            let (mut c3, mut a3) = (vec![0f32; w * 3], vec![0f32; w]);
            mpi.row(&maps, &rays, true, &mut c1, &mut a1, Some(&mut k1));
            mpi.row(&maps, &rays, false, &mut c2, &mut a2, Some(&mut k2));
            mpi.row(&maps, &rays, true, &mut c3, &mut a3, None);
            assert_eq!((&c1, &a1, &k1), (&c2, &a2, &k2), "row {y} at angle {angle}");
            assert_eq!(
                (&c1, &a1),
                (&c3, &a3),
                "the core's composite changed the render"
            );
            hits += a1.iter().filter(|&&a| a > 0.0).count();
        }
        assert!(
            hits > 0 && hits < w * h,
            "a partial view: {hits} pixels covered"
        );
    }
    Ok(())
}

#[test]
fn empty_blocks_hold_only_transparent_footprints_and_skipping_them_changes_nothing() -> Result<()> {
    // Planes empty in squares of 16 texels whose edges are the blocks' (the bordered
    // texture's texel x + 1 is the plane's x), so that the last row and column of a block
    // reach into the next square.
    let (w, h, d) = (50, 37, 6);
    let (colours, mut sel) = layers(d, w * h);
    for (i, s) in sel.iter_mut().enumerate() {
        let (z, x, y) = (i / (w * h), i % w, (i / w) % h);
        if ((x + 1) / 16 + (y + 1) / 16 + z) % 2 == 0 {
            *s = 0.0;
        }
    }
    let inv = crate::geometry::inverse_depths(0.5, f64::INFINITY, d);
    let mut mpi = Mpi::from_layers(camera(w as u32, h as u32, DVec3::ZERO), inv, &colours, &sel)?;
    mpi.margin = 5;
    let mut empty = 0;
    for t in mpi.textures() {
        // Every bilinear footprint (top-left texel (x, y) of the bordered texture) whose
        // block is not occupied sees four zero alphas.
        for y in 0..t.height + 1 {
            for x in 0..t.width + 1 {
                if t.occupied[(y >> BLOCK_SHIFT) * t.blocks + (x >> BLOCK_SHIFT)] {
                    continue;
                }
                let i = y * t.stride + x;
                for k in [i, i + 1, i + t.stride, i + t.stride + 1] {
                    assert_eq!(t.data[k][3], 0.0, "texel {k} in an empty block");
                }
            }
        }
        empty += t.occupied.iter().filter(|&&o| !o).count();
    }
    assert!(empty > 0, "no block is empty");
    let mut full = mpi.clone();
    full.textures();
    for t in full.textures.get_mut().into_iter().flatten() {
        t.occupied.iter_mut().for_each(|o| *o = true);
    }
    for centre in [DVec3::new(0.2, -0.1, 0.1), DVec3::new(-0.3, 0.2, -0.3)] {
        let cam = camera(w as u32, h as u32, centre);
        let (c1, a1, k1) = mpi.render_with_core(&cam);
        let (c2, a2, k2) = full.render_with_core(&cam);
        assert_eq!((&c1.data, &a1, &k1), (&c2.data, &a2, &k2), "at {centre}");
    }
    Ok(())
}

#[test]
fn runs_hold_every_ray_inside_and_little_else() {
    let asc: Vec<f64> = (0..50).map(|i| -1.0 + 0.04 * i as f64).collect();
    let desc: Vec<f64> = asc.iter().rev().cloned().collect();
    for (v, up) in [(&asc, true), (&desc, true), (&desc, false), (&asc, false)] {
        if v.windows(2).all(|p| p[0] <= p[1]) != up {
            continue;
        }
        for (s, o) in [
            (100.0, 50.0),
            (-80.0, 30.0),
            (25.0, -5.0),
            (0.0, 3.0),
            (0.0, -1.0),
        ] {
            let r = run(v, up, s, o, 40.0);
            for (i, x) in v.iter().enumerate() {
                let u = s * x + o;
                if (0.0..=40.0).contains(&u) {
                    assert!(r.contains(&i), "{i} (u = {u}) is inside but not in {r:?}");
                } else if r.contains(&i) {
                    assert!(
                        u > -1e-3 && u < 40.001,
                        "{i} (u = {u}) is outside but in {r:?}"
                    );
                }
            }
        }
    }
}

#[test]
fn alphas_telescope_and_survive_empty_planes() {
    let a = alphas(&[0.2, 0.0, 0.5, 0.3, 0.0]);
    assert_eq!(a[4], 0.0);
    assert!((a[3] - 1.0).abs() < 1e-7);
    assert!((a[2] - 0.5 / 0.8).abs() < 1e-7);
    assert_eq!(a[1], 0.0);
    assert!((a[0] - 0.2).abs() < 1e-7);
    assert_eq!(alphas(&[0.0, 0.0]), vec![0.0, 0.0]);
}

#[test]
fn planes_move_with_exact_parallax() -> Result<()> {
    // One opaque plane at depth 4 with a vertical edge at column 10 (left 0, right 1);
    // a camera moved by b = 0.5 along x sees it shifted by fx * b / depth = 5 pixels.
    let (w, h) = (40u32, 8u32);
    let cam = camera(w, h, DVec3::ZERO);
    let mut plane = vec![0f32; (w * h * 4) as usize];
    for y in 0..h as usize {
        for x in 0..w as usize {
            let px = &mut plane[(y * w as usize + x) * 4..][..4];
            px.copy_from_slice(&[if x >= 10 { 1.0 } else { 0.0 }, 0.0, 0.0, 1.0]);
        }
    }
    let mpi = Mpi::new(cam, vec![0.25], vec![plane.clone()])?;
    let moved = camera(w, h, DVec3::new(0.5, 0.0, 0.0));
    let (img, _) = mpi.render(&moved);
    let red = |x: usize| img.data[(3 * w as usize + x) * 3];
    assert_eq!((red(4), red(5)), (0.0, 1.0), "edge moved to column 5");
    // At infinity a translation moves nothing.
    let far = Mpi::new(cam, vec![0.0], vec![plane])?;
    let (img, _) = far.render(&moved);
    let red = |x: usize| img.data[(3 * w as usize + x) * 3];
    assert_eq!((red(9), red(10)), (0.0, 1.0));
    Ok(())
}

#[test]
fn the_directory_format_round_trips() -> Result<()> {
    let (w, h, d) = (9, 4, 3);
    let (colours, sel) = layers(d, w * h);
    let inv = vec![0.5, 0.25, 0.0];
    let cam = camera(w as u32, h as u32, DVec3::new(0.1, -0.2, 0.3));
    let mut mpi = Mpi::from_layers(cam, inv, &colours, &sel)?;
    mpi.margin = 1;
    let dir = tempfile::tempdir().map_err(|e| Error::io(Path::new("tmp"), e))?;
    io::write(&mpi, dir.path())?;
    let back = io::read(dir.path())?;
    assert_eq!((&back.inv_depths, back.margin), (&mpi.inv_depths, 1));
    assert!((back.camera.pose.translation - cam.pose.translation).length() < 1e-12);
    for (a, b) in back.planes().iter().zip(mpi.planes()) {
        assert!(a
            .iter()
            .zip(b)
            .all(|(x, y)| (x - y).abs() <= 0.5 / 255.0 + 1e-6));
    }
    // A plane of the wrong size is refused, naming the file.
    std::fs::copy(
        dir.path().join("plane_00.png"),
        dir.path().join("plane_01.png"),
    )
    .map_err(|e| Error::io(dir.path(), e))?;
    crate::imageio::save_rgb8_png(&dir.path().join("plane_02.png"), 2, 2, &[0; 12])?;
    let err = io::read(dir.path()).expect_err("a 2x2 plane").to_string();
    assert!(err.contains("plane_02.png") && err.contains("2x2"), "{err}");
    let json = dir.path().join(io::JSON_NAME);
    let text = std::fs::read_to_string(&json).map_err(|e| Error::io(&json, e))?;
    // Planes out of order, or named outside the directory, are refused.
    for (from, to, says) in [
        ("0.25,", "0.75,", "near to far"),
        ("\"plane_01.png\"", "\"../plane_01.png\"", "not a file name"),
        ("\"plane_01.png\"", "\"/etc/passwd\"", "not a file name"),
        ("\"plane_01.png\"", "\"a\\\\b.png\"", "not a file name"),
    ] {
        let bad = text.replace(from, to);
        assert_ne!(bad, text, "{from} not in mpi.json");
        std::fs::write(&json, &bad).map_err(|e| Error::io(&json, e))?;
        let err = io::read(dir.path()).expect_err(to).to_string();
        assert!(err.contains("mpi.json") && err.contains(says), "{err}");
    }
    // A margin that leaves nothing of the image is refused, naming the file.
    let text = text.replace("\"margin\": 1", "\"margin\": 2");
    std::fs::write(&json, text).map_err(|e| Error::io(&json, e))?;
    let err = io::read(dir.path())
        .expect_err("a margin of 2 on 4 rows")
        .to_string();
    assert!(
        err.contains("mpi.json") && err.contains("margin of 2"),
        "{err}"
    );
    Ok(())
}

#[test]
fn base64_matches_rfc_4648() {
    let cases = [
        ("", ""),
        ("f", "Zg=="),
        ("fo", "Zm8="),
        ("foo", "Zm9v"),
        ("foobar", "Zm9vYmFy"),
    ];
    for (plain, want) in cases {
        assert_eq!(viewer::base64(plain.as_bytes()), want);
    }
    assert_eq!(viewer::base64(&[255, 254, 253, 0]), "//79AA==");
}

#[test]
fn blending_copies_of_one_mpi_gives_it_back_and_8_bits_keep_40_db() -> Result<()> {
    let (w, h, d) = (24, 16, 32);
    let (colours, sel) = layers(d, w * h);
    let inv = crate::geometry::inverse_depths(1.0, f64::INFINITY, d);
    let cam = camera(w as u32, h as u32, DVec3::ZERO);
    let mpi = Mpi::from_layers(cam, inv, &colours, &sel)?;
    let dir = tempfile::tempdir().map_err(|e| Error::io(Path::new("tmp"), e))?;
    io::write(&mpi, dir.path())?;
    let back = io::read(dir.path())?;
    let psnr = crate::metrics::psnr(&back.composite(), &mpi.composite());
    assert!(psnr >= 40.0, "8-bit planes: {psnr:.1} dB");
    let moved = camera(w as u32, h as u32, DVec3::new(0.05, 0.02, 0.0));
    let (one, a) = mpi.render(&moved);
    let two = render_blend(&[mpi.clone(), mpi.clone()], &moved);
    for (p, &ap) in a.iter().enumerate() {
        for c in 0..3 {
            let want = if ap > 1e-12 {
                one.data[p * 3 + c] / ap
            } else {
                0.0
            };
            assert!((two.data[p * 3 + c] - want).abs() < 1e-5, "pixel {p}");
        }
    }
    Ok(())
}

use std::path::Path;

/// An MPI of one opaque plane at inverse depth 1 in `camera`, all of colour `rgb`.
fn flat(camera: Camera, rgb: [f32; 3]) -> Result<Mpi> {
    let n = camera.intrinsics.width as usize * camera.intrinsics.height as usize;
    let colours: Vec<f32> = rgb.iter().flat_map(|&c| vec![c; n]).collect();
    Mpi::from_layers(camera, vec![1.0], &colours, &vec![1.0; n])
}

#[test]
fn the_core_render_leaves_the_margin_out() -> Result<()> {
    let (w, h, m) = (24u32, 16u32, 8u32);
    let base = camera(w, h, DVec3::ZERO);
    let mut mpi = flat(with_margin(&base, m), [0.2, 0.4, 0.6])?;
    mpi.margin = m;
    let (img, alpha, core) = mpi.render_with_core(&mpi.camera);
    let (mw, mh) = ((w + 2 * m) as usize, (h + 2 * m) as usize);
    let mut inside = 0;
    for y in 0..mh {
        for x in 0..mw {
            let p = y * mw + x;
            let own = (m as usize..(m + w) as usize).contains(&x)
                && (m as usize..(m + h) as usize).contains(&y);
            assert!((alpha[p] - 1.0).abs() < 1e-6, "alpha at ({x}, {y})");
            let want = if own { 1.0 } else { 0.0 };
            assert!(
                (core[p * 4 + 3] - want).abs() < 1e-6,
                "core alpha at ({x}, {y})"
            );
            for c in 0..3 {
                let v = img.data[p * 3 + c] * want;
                assert!(
                    (core[p * 4 + c] - v).abs() < 1e-6,
                    "core colour at ({x}, {y})"
                );
            }
            inside += own as usize;
        }
    }
    assert_eq!(inside, (w * h) as usize);
    mpi.margin = 0;
    let (img, alpha, core) = mpi.render_with_core(&mpi.camera);
    for p in 0..alpha.len() {
        assert_eq!(
            core[p * 4 + 3],
            alpha[p],
            "without a margin the core is all"
        );
        assert_eq!(core[p * 4..p * 4 + 3], img.data[p * 3..p * 3 + 3]);
    }
    Ok(())
}

#[test]
fn a_blend_prefers_a_farther_view_to_a_nearer_margin() -> Result<()> {
    let (w, h, m) = (24u32, 16u32, 8u32);
    let (red, blue) = ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0]);
    let mut a = flat(with_margin(&camera(w, h, DVec3::ZERO), m), red)?;
    a.margin = m;
    let b = flat(camera(w, h, DVec3::new(0.4, 0.0, 0.0)), blue)?;
    // Nearer to a than to b; 8 pixels of parallax to a on the plane at depth 1.
    let view = camera(w, h, DVec3::new(0.2, 0.0, 0.0));
    let (da, db) = (0.2f64, 0.2f64);
    let img = render_blend(&[a.clone(), b.clone()], &view);
    let (_, aa, ka) = a.render_with_core(&view);
    let (_, ab, _) = b.render_with_core(&view);
    let (wa, wb) = (1.0 / da.powi(2), 1.0 / db.powi(2));
    let delta = MARGIN_BLEND_WEIGHT;
    let mut margin_only = 0;
    for p in 0..(w * h) as usize {
        let px = &img.data[p * 3..p * 3 + 3];
        assert!(px.iter().all(|v| v.is_finite() && (0.0..=1.0).contains(v)));
        let (own_a, full_a) = (ka[p * 4 + 3] as f64, aa[p] as f64);
        if full_a > 0.99 && own_a < 1e-6 && ab[p] > 0.99 {
            // a's margin against b's view: b wins.
            margin_only += 1;
            let want = wb * (1.0 + delta) / (wb * (1.0 + delta) + wa * delta);
            assert!(
                (px[2] as f64 - want).abs() < 1e-4,
                "pixel {p}: {px:?}, want blue {want}"
            );
            assert!(px[2] > 0.8, "pixel {p}: {px:?}: the nearer margin won");
        }
        if own_a > 0.99 && ab[p] > 0.99 {
            assert!(
                (px[0] - 0.5).abs() < 1e-4,
                "both views, equal distance: {px:?}"
            );
        }
    }
    assert!(
        margin_only > 0,
        "no pixel sees only a's margin and b's view"
    );
    Ok(())
}

#[test]
fn the_viewer_blends_with_the_cpus_margin_weight() {
    let want = format!("const DELTA = \"{MARGIN_BLEND_WEIGHT}\";");
    assert!(
        viewer::INDEX_HTML.contains(&want),
        "viewer.html lacks {want}"
    );
}

#[test]
fn with_composite_moves_the_colours_to_a_given_composite_and_keeps_the_alphas() -> Result<()> {
    let (w, h, d) = (7, 5, 6);
    let n = w * h;
    let (mut colours, sel) = layers(d, n);
    // Colours within [0.2, 0.8], so a shift of at most 0.2 clamps nothing.
    colours.iter_mut().for_each(|c| *c = 0.2 + 0.6 * *c);
    let inv = crate::geometry::inverse_depths(1.0, f64::INFINITY, d);
    let mpi = Mpi::from_layers(camera(w as u32, h as u32, DVec3::ZERO), inv, &colours, &sel)?;
    let mut target = mpi.composite();
    let shifts = values(n * 3, 3);
    for (t, s) in target.data.iter_mut().zip(&shifts) {
        *t += 0.4 * (s - 0.5);
    }
    let moved = mpi.with_composite(&target)?;
    let got = moved.composite();
    for (p, (a, b)) in got.data.iter().zip(&target.data).enumerate() {
        assert!((a - b).abs() < 1e-5, "composite {p}: {a} against {b}");
    }
    for (a, b) in moved.planes().iter().zip(mpi.planes()) {
        assert!(a.chunks(4).zip(b.chunks(4)).all(|(x, y)| x[3] == y[3]));
    }
    // Colours that would leave [0, 1] are clamped; a target of another size is refused.
    let white = RgbImage {
        width: w as u32,
        height: h as u32,
        data: vec![1.0; n * 3],
    };
    let clamped = mpi.with_composite(&white)?;
    assert!(clamped
        .planes()
        .iter()
        .all(|p| p.iter().all(|v| (0.0..=1.0).contains(v))));
    let (before, after) = (mpi.composite(), clamped.composite());
    assert!(after.data.iter().zip(&before.data).all(|(a, b)| a >= b));
    let small = RgbImage::new(3, 2);
    assert!(mpi.with_composite(&small).is_err());
    // With a margin, only the reference image moves: the margin's texels keep their
    // colours (no photograph shows them) and the composite inside is the target.
    let mut framed = mpi.clone();
    framed.margin = 1;
    let moved = framed.with_composite(&target)?;
    let got = moved.composite();
    for p in 0..n {
        let (x, y) = (p % w, p / w);
        let inside = x >= 1 && x + 1 < w && y >= 1 && y + 1 < h;
        for z in 0..d {
            let (a, b) = (
                &moved.planes()[z][p * 4..p * 4 + 4],
                &mpi.planes()[z][p * 4..p * 4 + 4],
            );
            assert_eq!(inside, a != b, "texel {p} on plane {z}");
        }
        if inside {
            for c in 0..3 {
                assert!((got.data[p * 3 + c] - target.data[p * 3 + c]).abs() < 1e-5);
            }
        }
    }
    Ok(())
}

#[test]
fn box_means_match_a_direct_sum_clipped_at_the_border() {
    let (w, h, d, r) = (9, 6, 2, 2);
    let x: Vec<f64> = values(d * w * h, 5).into_iter().map(f64::from).collect();
    let got = smooth::box_mean_planes(&x, d, (w, h), r);
    for z in 0..d {
        for y in 0..h {
            for i in 0..w {
                let (mut sum, mut count) = (0f64, 0usize);
                for yy in y.saturating_sub(r)..=(y + r).min(h - 1) {
                    for ii in i.saturating_sub(r)..=(i + r).min(w - 1) {
                        sum += x[z * w * h + yy * w + ii];
                        count += 1;
                    }
                }
                let p = z * w * h + y * w + i;
                assert!((got[p] - sum / count as f64).abs() < 1e-12, "texel {p}");
            }
        }
    }
}

#[test]
fn smoothing_averages_the_selection_and_keeps_colours_and_flat_profiles() -> Result<()> {
    let (w, h, d, r) = (7, 5, 4, 1);
    let n = w * h;
    let (colours, sel) = layers(d, n);
    let inv = crate::geometry::inverse_depths(1.0, f64::INFINITY, d);
    let cam = camera(w as u32, h as u32, DVec3::ZERO);
    let mpi = Mpi::from_layers(cam, inv.clone(), &colours, &sel)?;
    assert_eq!(mpi.with_smoothed_selection(0)?.planes(), mpi.planes());
    let smoothed = mpi.with_smoothed_selection(r)?;
    // The smoothed MPI's composite weighs each plane's red by the box mean of its selection.
    let red: Vec<f32> = (0..d * n).map(|i| colours[i / n * 3 * n + i % n]).collect();
    let composite = smoothed.composite();
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            let mut want = 0f64;
            for z in 0..d {
                let (mut sum, mut count) = (0f64, 0usize);
                for yy in y.saturating_sub(r)..=(y + r).min(h - 1) {
                    for xx in x.saturating_sub(r)..=(x + r).min(w - 1) {
                        sum += sel[z * n + yy * w + xx] as f64;
                        count += 1;
                    }
                }
                want += sum / count as f64 * red[z * n + p] as f64;
            }
            let got = composite.data[p * 3];
            assert!(
                (got as f64 - want).abs() < 1e-5,
                "texel {p}: {got} vs {want}"
            );
            for (a, b) in smoothed.planes().iter().zip(mpi.planes()) {
                assert_eq!(a[p * 4..p * 4 + 3], b[p * 4..p * 4 + 3], "colours at {p}");
            }
        }
    }
    // One depth profile everywhere stays as it is.
    let flat_sel: Vec<f32> = (0..d * n).map(|i| [0.1, 0.2, 0.3, 0.4][i / n]).collect();
    let flat = Mpi::from_layers(cam, inv, &colours, &flat_sel)?;
    for (a, b) in flat
        .with_smoothed_selection(3)?
        .planes()
        .iter()
        .zip(flat.planes())
    {
        for (u, v) in a.iter().zip(b) {
            assert!((u - v).abs() < 1e-6);
        }
    }
    Ok(())
}

#[test]
fn smoothing_keeps_a_texels_empty_planes_empty() -> Result<()> {
    let (w, h, d) = (4, 3, 3);
    let n = w * h;
    let (colours, _) = layers(d, n);
    // Every texel selects planes 0 and 2 as 0.25 / 0.75, but texel 5 leaves plane 0 out.
    let mut sel: Vec<f32> = (0..d * n).map(|i| [0.25, 0.0, 0.75][i / n]).collect();
    sel[5] = 0.0;
    sel[2 * n + 5] = 1.0;
    let inv = crate::geometry::inverse_depths(1.0, f64::INFINITY, d);
    let mpi = Mpi::from_layers(camera(w as u32, h as u32, DVec3::ZERO), inv, &colours, &sel)?;
    let smoothed = mpi.with_smoothed_selection(1)?;
    let alpha = |z: usize, p: usize| smoothed.planes()[z][p * 4 + 3];
    assert_eq!(alpha(0, 5), 0.0, "texel 5's empty plane filled");
    assert_eq!(
        (0..n).map(|p| alpha(1, p)).sum::<f32>(),
        0.0,
        "plane 1 filled"
    );
    // Texel 0's box (texels 0, 1, 4, 5) holds texel 5's 0 / 1: plane 0 has 0.75 / 4.
    assert!((alpha(0, 0) - 0.1875).abs() < 1e-6, "{}", alpha(0, 0));
    Ok(())
}

/// What `camera` sees of the plane `z = depth` painted with a smooth pattern (colours in
/// [0.1, 0.9], exact per pixel centre).
fn painted_plane(camera: &Camera, depth: f64) -> RgbImage {
    let k = &camera.intrinsics;
    let (w, h) = (k.width as usize, k.height as usize);
    let centre = camera.pose.centre();
    let mut data = Vec::with_capacity(w * h * 3);
    for y in 0..h {
        for x in 0..w {
            let ray = DVec3::new(
                (x as f64 + 0.5 - k.cx) / k.fx,
                (y as f64 + 0.5 - k.cy) / k.fy,
                1.0,
            );
            let p = centre + ray * (depth - centre.z);
            for ch in 0..3 {
                let phase = ch as f64 * 2.1;
                data.push(
                    (0.5 + 0.4 * (10.0 * p.x + phase).sin() * (6.0 * p.y - phase).cos()) as f32,
                );
            }
        }
    }
    RgbImage {
        width: w as u32,
        height: h as u32,
        data,
    }
}

#[test]
fn the_photographs_agreement_peaks_on_the_plane_the_surface_lies_on() -> Result<()> {
    let (w, h, margin) = (24u32, 20u32, 3u32);
    let inv = vec![1.0 / 1.2, 1.0 / 2.0, 1.0 / 3.5];
    let reference = camera(w, h, DVec3::ZERO);
    // On one side of the reference, so that their errors do not cancel out.
    let mut others: Vec<Camera> = [0.15, 0.3, 0.45]
        .iter()
        .map(|&b| camera(w, h, DVec3::new(b, 0.05 * b, 0.0)))
        .collect();
    let photo = painted_plane(&reference, 2.0);
    let mut images: Vec<RgbImage> = others.iter().map(|c| painted_plane(c, 2.0)).collect();
    // One that sees an occluder (flat white): the closer half of the errors leaves it out.
    others.push(camera(w, h, DVec3::new(0.2, 0.0, 0.0)));
    images.push(RgbImage {
        width: w,
        height: h,
        data: vec![0.95; (w * h * 3) as usize],
    });
    // And one that sees none of it: it is not among the errors.
    others.push(camera(w, h, DVec3::new(50.0, 0.0, 0.0)));
    images.push(painted_plane(&others[4], 2.0));
    let sources: Vec<crate::sweep::Source> = (others.iter().zip(&images))
        .map(|(camera, image)| crate::sweep::Source { camera, image })
        .collect();
    let photo = crate::sweep::Source {
        camera: &reference,
        image: &photo,
    };
    // An MPI with its margin, every texel selecting the three planes alike.
    let cam = with_margin(&reference, margin);
    let (mw, mh) = (
        cam.intrinsics.width as usize,
        cam.intrinsics.height as usize,
    );
    let n = mw * mh;
    let colours = values(3 * 3 * n, 3);
    let sel = vec![1.0 / 3.0; 3 * n];
    let mut mpi = Mpi::from_layers(cam, inv, &colours, &sel)?;
    mpi.margin = margin;
    let f = mpi.agreement(photo, &sources, 0.1)?;
    let m = margin as usize;
    // The margin has no photograph: its factors stay 1.
    for (p, _) in (0..n).map(|p| (p, ())).filter(|&(p, _)| {
        let (x, y) = (p % mw, p / mw);
        x < m || y < m || x >= mw - m || y >= mh - m
    }) {
        assert!((0..3).all(|z| f[z * n + p] == 1.0), "margin texel {p}");
    }
    // Inside, away from where the far views leave the image, the surface's plane agrees.
    let reweighed = mpi.with_photo_agreement(photo, &sources, 0.1)?;
    let share = |mpi: &Mpi, p: usize, z: usize| {
        let a = |k: usize| mpi.planes()[k][p * 4 + 3] as f64;
        a(z) * (0..z).map(|k| 1.0 - a(k)).product::<f64>()
    };
    let mut checked = 0;
    for y in m + 4..mh - m - 4 {
        for x in m + 6..mw - m - 6 {
            let p = y * mw + x;
            assert!(f[n + p] > 0.8, "texel {p}: {}", f[n + p]);
            let (f0, f1, f2) = (f[p], f[n + p], f[2 * n + p]);
            assert!(f0 < 0.5 * f1 && f2 < 0.5 * f1, "texel {p}: {f0} {f1} {f2}");
            let shares: Vec<f64> = (0..3).map(|z| share(&reweighed, p, z)).collect();
            assert!(
                (shares.iter().sum::<f64>() - 1.0).abs() < 1e-5,
                "coverage at {p}"
            );
            // The flat selection becomes the factors, normalized.
            let total = (f0 + f1 + f2) as f64;
            for (z, fz) in [f0, f1, f2].into_iter().enumerate() {
                let want = fz as f64 / total;
                assert!((shares[z] - want).abs() < 1e-5, "texel {p}: {shares:?}");
            }
            checked += 1;
        }
    }
    assert!(checked >= 20);
    assert!(mpi.with_photo_agreement(photo, &sources, 0.0).is_err());
    assert!(mpi.with_photo_agreement(photo, &sources, f64::NAN).is_err());
    Ok(())
}

#[test]
fn reweighing_by_ones_keeps_the_selection_and_by_a_plane_moves_it_there() -> Result<()> {
    let (w, h, d) = (5, 4, 3);
    let n = w * h;
    let (colours, sel) = layers(d, n);
    let inv = crate::geometry::inverse_depths(1.0, f64::INFINITY, d);
    let mpi = Mpi::from_layers(camera(w as u32, h as u32, DVec3::ZERO), inv, &colours, &sel)?;
    let same = mpi.with_reweighed_selection(&vec![1.0; d * n])?;
    for (a, b) in same.planes().iter().zip(mpi.planes()) {
        for (u, v) in a.iter().zip(b) {
            assert!((u - v).abs() < 1e-6);
        }
    }
    // Only plane 2 agrees: every texel selects it alone; colours stay.
    let only: Vec<f32> = (0..d * n)
        .map(|i| if i / n == 2 { 0.3 } else { 0.0 })
        .collect();
    let moved = mpi.with_reweighed_selection(&only)?;
    for p in 0..n {
        let a: Vec<f32> = moved.planes().iter().map(|pl| pl[p * 4 + 3]).collect();
        assert_eq!(a, vec![0.0, 0.0, 1.0], "texel {p}");
        for (x, y) in moved.planes().iter().zip(mpi.planes()) {
            assert_eq!(x[p * 4..p * 4 + 3], y[p * 4..p * 4 + 3]);
        }
    }
    // No plane agrees anywhere: the texel keeps its own selection.
    let none = mpi.with_reweighed_selection(&vec![0.0; d * n])?;
    assert_eq!(none.planes(), mpi.planes());
    Ok(())
}
