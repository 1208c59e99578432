use super::*;
use crate::camera::{Intrinsics, WorldToCamera};
use glam::DMat3;

fn grid() -> PriorGrid {
    PriorGrid::zeros(DVec3::new(-1.0, -1.0, 1.0), DVec3::new(1.0, 1.0, 3.0), 5).unwrap()
}

#[test]
fn zero_grid_changes_nothing() {
    let g = grid();
    let mut s = vec![0.1, 0.6, 0.3];
    let cells: Vec<Cell> = [1.5, 2.0, 2.5]
        .iter()
        .map(|&z| g.locate(DVec3::new(0.2, -0.3, z)))
        .collect();
    g.reweigh(&mut s, &cells);
    for (a, b) in s.iter().zip([0.1, 0.6, 0.3]) {
        assert!((a - b).abs() < 1e-7, "{a} {b}");
    }
}

#[test]
fn trilinear_reproduces_a_linear_field() {
    let mut g = grid();
    let [nx, ny, _] = g.dims;
    for (i, v) in g.values.iter_mut().enumerate() {
        let (x, y, z) = (i % nx, (i / nx) % ny, i / (nx * ny));
        let p = g.origin + DVec3::new(x as f64, y as f64, z as f64) * g.cell;
        *v = (0.5 * p.x - 2.0 * p.y + p.z) as f32;
    }
    for p in [DVec3::new(0.13, 0.77, 2.31), DVec3::new(-0.9, 0.0, 1.01)] {
        let want = 0.5 * p.x - 2.0 * p.y + p.z;
        let got = g.value(g.locate(p)) as f64;
        assert!((got - want).abs() < 1e-5, "{got} {want}");
    }
    // Outside the box: the nearest face's value.
    let inside = g.value(g.locate(DVec3::new(1.0, 0.0, 2.0)));
    assert_eq!(g.value(g.locate(DVec3::new(7.0, 0.0, 2.0))), inside);
    assert!(g
        .value(g.locate(DVec3::new(f64::INFINITY, 0.0, 2.0)))
        .is_finite());
}

#[test]
fn reweigh_is_the_softmax_of_log_selection_plus_bias() {
    let mut s = vec![0.2, 0.5, 0.3, 0.0];
    let b = [1.0, -0.5, 0.25, 5.0];
    reweigh_with(&mut s, &b, 1.0);
    let e: Vec<f64> = [0.2f64, 0.5, 0.3, 0.0]
        .iter()
        .zip(b)
        .map(|(s, b)| s * (b as f64).exp())
        .collect();
    let sum: f64 = e.iter().sum();
    for (a, w) in s.iter().zip(&e) {
        assert!((*a as f64 - w / sum).abs() < 1e-6);
    }
    // Extreme log-weights stay finite and sum to 1; an all-zero selection stays zero.
    let mut s = vec![0.5, 0.5];
    reweigh_with(&mut s, &[1e30, -1e30], 1.0);
    assert!((s[0] + s[1] - 1.0).abs() < 1e-6 && s.iter().all(|v| v.is_finite()));
    let mut z = vec![0.0, 0.0];
    reweigh_with(&mut z, &[1.0, 2.0], 1.0);
    assert_eq!(z, vec![0.0, 0.0]);
}

#[test]
fn sharpness_is_an_exponent_of_the_selection() {
    let s0 = [0.2f32, 0.5, 0.3, 0.0];
    let b = [1.0, -0.5, 0.25, 5.0];
    for g in [0.25f32, 0.5, 2.0, 8.0] {
        let mut s = s0.to_vec();
        reweigh_with(&mut s, &b, g);
        let e: Vec<f64> = (s0.iter().zip(b))
            .map(|(&v, b)| match v > 0.0 {
                true => (v as f64).powf(g as f64) * (b as f64).exp(),
                false => 0.0,
            })
            .collect();
        let sum: f64 = e.iter().sum();
        for (a, w) in s.iter().zip(&e) {
            assert!((*a as f64 - w / sum).abs() < 1e-6, "g {g}: {a} {}", w / sum);
        }
    }
    // Near 1 it is the plain reweighing; tiny and extreme selections stay finite.
    let (mut a, mut c) = (s0.to_vec(), s0.to_vec());
    reweigh_with(&mut a, &b, 1.0);
    reweigh_with(&mut c, &b, 1.0 + 1e-6);
    for (x, y) in a.iter().zip(&c) {
        assert!((x - y).abs() < 1e-5);
    }
    let mut tiny = vec![1e-38f32, 1e-30, 0.0, 1.0];
    reweigh_with(&mut tiny, &[12.0, -12.0, 0.0, 0.0], 8.0);
    assert!(tiny.iter().all(|v| v.is_finite()) && (tiny.iter().sum::<f32>() - 1.0).abs() < 1e-6);
    let mut z = vec![0.0, 0.0];
    reweigh_with(&mut z, &[1.0, 2.0], 3.0);
    assert_eq!(z, vec![0.0, 0.0]);
}

/// The analytic gradient against central differences of the L1 loss, by the cells and by
/// the sharpness, at the network's sharpness and away from it.
#[test]
fn ray_gradient_matches_finite_differences() {
    for sharpness in [1.0f32, 1.7, 0.6] {
        let mut g = grid();
        g.sharpness = sharpness;
        for (i, v) in g.values.iter_mut().enumerate() {
            *v = ((i * 37 % 11) as f32 - 5.0) * 0.1;
        }
        let s = [0.1f32, 0.4, 0.3, 0.2];
        let c = [
            [0.9f32, 0.1, 0.2],
            [0.2, 0.8, 0.3],
            [0.4, 0.4, 0.9],
            [0.7, 0.6, 0.1],
        ];
        let cells: Vec<Cell> = [1.2, 1.7, 2.2, 2.9]
            .iter()
            .map(|&z| g.locate(DVec3::new(0.31, -0.42, z)))
            .collect();
        let truth = [0.5f32, 0.45, 0.3];
        let (mut grad, mut grad_g) = (vec![0f32; g.values.len()], 0f32);
        g.ray_gradient(&s, &c, &cells, truth, 1.0, &mut grad, &mut grad_g);
        let loss = |g: &PriorGrid| {
            let (mut scratch, mut sg) = (vec![0f32; g.values.len()], 0f32);
            g.ray_gradient(&s, &c, &cells, truth, 1.0, &mut scratch, &mut sg) as f64
        };
        let h = 1e-3f32;
        let mut checked = 0;
        for (i, &gi) in grad.iter().enumerate() {
            if gi == 0.0 {
                continue;
            }
            let (mut up, mut down) = (g.clone(), g.clone());
            up.values[i] += h;
            down.values[i] -= h;
            let fd = (loss(&up) - loss(&down)) / (2.0 * h as f64);
            assert!((fd - gi as f64).abs() < 2e-3, "cell {i}: {fd} vs {gi}");
            checked += 1;
        }
        assert!(checked >= 8, "only {checked} cells had a gradient");
        let (mut up, mut down) = (g.clone(), g.clone());
        up.sharpness += h;
        down.sharpness -= h;
        let fd = (loss(&up) - loss(&down)) / (2.0 * h as f64);
        assert!(grad_g.abs() > 1e-3, "no sharpness gradient at {sharpness}");
        assert!(
            (fd - grad_g as f64).abs() < 2e-3,
            "sharpness {sharpness}: {fd} vs {grad_g}"
        );
    }
}

/// The plane points of a ray lie on it at the planes' camera depths.
#[test]
fn rays_are_located_at_their_plane_points() {
    let g = PriorGrid::zeros(DVec3::splat(-4.0), DVec3::splat(4.0), 65).unwrap();
    let pose = WorldToCamera::new_checked(DMat3::from_rotation_y(0.3), DVec3::new(0.1, -0.2, 0.5))
        .unwrap();
    let cam = Camera::global(Intrinsics::pinhole(50.0, 55.0, 16.0, 12.0, 32, 24), pose);
    let inv = [0.5, 0.4, 0.3];
    let cells = g.locate_rays(&cam, &inv, &[(7, 5)]);
    for (z, &rho) in inv.iter().enumerate() {
        let x = cam.unproject(DVec2::new(7.5, 5.5), 1.0 / rho);
        assert_eq!(cells[z], g.locate(x));
    }
}

/// Writes `arrays` with `meta` and reads the prior back through [`io::read`].
fn read_back(
    arrays: &[crate::tensorio::NamedArray],
    meta: Option<(&str, String)>,
) -> Result<Option<PriorGrid>> {
    let dir = tempfile::tempdir().map_err(|e| Error::Invalid(e.to_string()))?;
    let path = dir.path().join("m.safetensors");
    let meta = meta.map(|(k, v)| [(k.to_string(), v)].into_iter().collect());
    crate::tensorio::write_safetensors(&path, arrays, meta)?;
    let bytes = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
    let st =
        safetensors::SafeTensors::deserialize(&bytes).map_err(|e| Error::Invalid(e.to_string()))?;
    io::read(&path, &bytes, &st)
}

fn err_of(r: Result<Option<PriorGrid>>) -> String {
    r.expect_err("accepted").to_string()
}

#[test]
fn a_prior_file_round_trips_and_bad_ones_are_refused() {
    let mut g = grid();
    g.values
        .iter_mut()
        .enumerate()
        .for_each(|(i, v)| *v = i as f32 * 0.01);
    g.sharpness = 1.75;
    let (array, (key, json)) = io::to_file(&g);
    let back = read_back(std::slice::from_ref(&array), Some((key, json.clone())))
        .expect("read")
        .expect("a prior");
    assert_eq!(
        (back.dims, &back.values, back.sharpness),
        (g.dims, &g.values, g.sharpness)
    );
    // A placement written without a sharpness (before it existed) reads as 1.
    let plain = r#"{"origin":[-1,-1,1],"cell":0.5}"#.to_string();
    let old = read_back(std::slice::from_ref(&array), Some((key, plain))).expect("read");
    assert_eq!(old.map(|p| p.sharpness), Some(1.0));
    let wild = r#"{"origin":[0,0,0],"cell":1,"sharpness":100}"#.to_string();
    assert!(
        err_of(read_back(std::slice::from_ref(&array), Some((key, wild)))).contains("sharpness")
    );
    assert!((back.origin - g.origin).length() < 1e-12 && (back.cell - g.cell).abs() < 1e-12);
    assert_eq!(read_back(&[], None).expect("no prior"), None);
    let err = err_of;
    assert!(err(read_back(std::slice::from_ref(&array), None)).contains("needs both"));
    let mut nan = g.clone();
    nan.values[3] = f32::NAN;
    let (bad, _) = io::to_file(&nan);
    assert!(err(read_back(&[bad], Some((key, json.clone())))).contains("non-finite"));
    let flat = crate::tensorio::NamedArray::f32(io::TENSOR, &[g.values.len()], &g.values);
    assert!(err(read_back(&[flat], Some((key, json)))).contains("shape"));
    let cell0 = r#"{"origin":[0,0,0],"cell":0}"#.to_string();
    assert!(err(read_back(std::slice::from_ref(&array), Some((key, cell0)))).contains("positive"));
}
