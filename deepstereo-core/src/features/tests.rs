use super::*;
use crate::camera::{Camera, Intrinsics, WorldToCamera};
use crate::config::{Conv, SourceFeatures};
use crate::sweep::coords::sweep_coords;
use crate::sweep::{sweep, Region, Source};
use candle_core::{DType, Var};
use candle_nn::VarMap;
use glam::{DMat3, DVec3};

fn camera(x: f64, w: u32, h: u32) -> Camera {
    let intr = Intrinsics::pinhole(
        0.9 * w as f64,
        0.9 * w as f64,
        w as f64 / 2.0,
        h as f64 / 2.0,
        w,
        h,
    );
    let centre = DVec3::new(x, 0.03, 0.0);
    Camera {
        intrinsics: intr,
        pose: WorldToCamera::new_checked(DMat3::IDENTITY, -centre).expect("a pose"),
        rolling_shutter: None,
    }
}

fn image(w: u32, h: u32, seed: u32) -> RgbImage {
    let mut img = RgbImage::new(w, h);
    for (i, v) in img.data.iter_mut().enumerate() {
        let z = (i as u32)
            .wrapping_mul(2654435761)
            .wrapping_add(seed.wrapping_mul(97));
        *v = (z >> 8) as f32 / (1u32 << 24) as f32;
    }
    img
}

/// The warp of a map equal to the image reproduces the sweep's colours (same positions,
/// same taps, same zero padding), on a crop window as on the whole image.
#[test]
fn warping_the_image_as_a_map_gives_the_sweep() -> Result<()> {
    let (w, h) = (40u32, 30u32);
    let (target, source) = (camera(0.0, w, h), camera(0.2, w, h));
    let img = image(w, h, 1);
    let region = Region {
        x0: -3,
        y0: 2,
        width: 17,
        height: 11,
    };
    let planes = [0.05, 0.4, 1.3];
    let rgba = sweep(
        &target,
        region,
        &[Source {
            camera: &source,
            image: &img,
        }],
        &planes,
    );
    let coords = sweep_coords(&target, region, &[&source], &planes);
    let whole = Window {
        x0: 0,
        y0: 0,
        width: w as usize,
        height: h as usize,
    };
    let p = region.len();
    for window in [
        Some(whole),
        tap_window(&coords, region.len(), (w as usize, h as usize)),
    ] {
        let window = window.expect("the planes see the source");
        let map = padded_crop(&img, window);
        let op = FeatureWarp::new(&coords, planes.len(), (w as usize, h as usize), window)?;
        let out = op.apply(&map, 3); // [D, 3, P]
        if window == whole {
            let fm = FeatureMap {
                channels: 3,
                width: w as usize,
                height: h as usize,
                data: map.clone(),
            };
            let direct = sample_map(&fm, &coords, planes.len());
            assert_eq!(direct, out, "sample_map against the taps");
        }
        for d in 0..planes.len() {
            for c in 0..3 {
                for i in 0..p {
                    let (a, b) = (out[(d * 3 + c) * p + i], rgba[(d * 4 + c) * p + i]);
                    assert!(
                        (a - b).abs() < 1e-5,
                        "plane {d} channel {c} pixel {i}: {a} vs {b}"
                    );
                }
            }
        }
    }
    Ok(())
}

/// A window that misses a tap is refused.
#[test]
fn a_window_missing_a_tap_is_an_error() {
    let coords = [5.0, 5.0]; // one plane, one pixel at (5, 5)
    let window = Window {
        x0: 0,
        y0: 0,
        width: 4,
        height: 4,
    };
    assert!(FeatureWarp::new(&coords, 1, (10, 10), window).is_err());
}

/// The features of a crop (padded by the radius) equal the whole image's inside it.
#[test]
fn crop_features_equal_the_whole_images() -> Result<()> {
    let cfg = SourceFeatures {
        convs: vec![
            Conv {
                kernel: 3,
                channels: 4,
            },
            Conv {
                kernel: 5,
                channels: 2,
            },
        ],
    };
    let varmap = VarMap::new();
    let vb = VarBuilder::from_varmap(&varmap, DType::F32, &Device::Cpu);
    let net = FeatureNet::new(&cfg, vb)?;
    let img = image(23, 17, 3);
    let whole = net.image_features(&img, &Device::Cpu)?;
    let r = net.radius() as i64;
    let crop = Window {
        x0: 15,
        y0: -2,
        width: 8,
        height: 9,
    };
    let padded = Window {
        x0: crop.x0 - r,
        y0: crop.y0 - r,
        width: crop.width + 2 * r as usize,
        height: crop.height + 2 * r as usize,
    };
    let x = Tensor::from_vec(padded_crop(&img, padded), padded.shape(), &Device::Cpu)?;
    let f = net.forward(&x.unsqueeze(0)?)?.squeeze(0)?; // [2, 9, 8]
    let f = f.to_vec3::<f32>()?;
    for (c, plane) in f.iter().enumerate() {
        for (y, row) in plane.iter().enumerate() {
            for (x, &v) in row.iter().enumerate() {
                let (ix, iy) = (crop.x0 + x as i64, crop.y0 + y as i64);
                if ix < 0 || iy < 0 || ix >= 23 || iy >= 17 {
                    continue;
                }
                let want = whole.data[(c * 17 + iy as usize) * 23 + ix as usize];
                assert!((v - want).abs() < 1e-5, "({c}, {ix}, {iy}): {v} vs {want}");
            }
        }
    }
    Ok(())
}

/// The warp's gradient against central finite differences of `sum(y * g)`.
#[test]
fn warp_gradient_matches_finite_differences() -> Result<()> {
    let (w, h) = (12u32, 9u32);
    let (target, source) = (camera(0.0, w, h), camera(0.15, w, h));
    let region = Region {
        x0: 0,
        y0: 0,
        width: 6,
        height: 5,
    };
    let planes = [0.1, 0.9];
    let coords = sweep_coords(&target, region, &[&source], &planes);
    let window = tap_window(&coords, region.len(), (w as usize, h as usize)).expect("taps");
    let op = FeatureWarp::new(&coords, planes.len(), (w as usize, h as usize), window)?;
    let c = 2;
    let n = c * window.width * window.height;
    let f0: Vec<f32> = (0..n).map(|i| ((i * 37 % 101) as f32) / 101.0).collect();
    let g: Vec<f32> = (0..planes.len() * c * region.len())
        .map(|i| ((i * 13 % 7) as f32) - 3.0)
        .collect();
    let var = Var::from_vec(f0.clone(), (c, window.height, window.width), &Device::Cpu)?;
    let gt = Tensor::from_vec(g.clone(), (planes.len(), c, region.len()), &Device::Cpu)?;
    let loss = warp(var.as_tensor(), &op)?.mul(&gt)?.sum_all()?;
    let grads = loss.backward()?;
    let dx = grads
        .get(var.as_tensor())
        .expect("a gradient")
        .flatten_all()?
        .to_vec1::<f32>()?;
    let value = |f: &[f32]| -> f64 {
        op.apply(f, c)
            .iter()
            .zip(&g)
            .map(|(&y, &gv)| (y * gv) as f64)
            .sum()
    };
    for i in (0..n).step_by(3) {
        let (mut a, mut b) = (f0.clone(), f0.clone());
        a[i] += 0.25;
        b[i] -= 0.25;
        let fd = (value(&a) - value(&b)) / 0.5;
        assert!(
            (fd - dx[i] as f64).abs() < 1e-3,
            "element {i}: {fd} vs {}",
            dx[i]
        );
    }
    Ok(())
}

/// Empty regions and empty maps give empty or zero outputs, not a panic.
#[test]
fn empty_regions_and_maps_are_not_a_panic() -> Result<()> {
    let none = Window {
        x0: 0,
        y0: 0,
        width: 0,
        height: 0,
    };
    let op = FeatureWarp::new(&[], 2, (4, 4), none)?;
    assert!(op.apply(&[], 3).is_empty());
    let op = FeatureWarp::new(&[0.5, 0.5], 1, (0, 0), none)?; // one pixel, an empty image
    assert_eq!(op.apply(&[], 2), vec![0.0; 2]);
    let map = FeatureMap {
        channels: 2,
        width: 0,
        height: 0,
        data: vec![],
    };
    assert!(sample_map(&map, &[], 3).is_empty());
    assert_eq!(sample_map(&map, &[1.0, 1.0], 1), vec![0.0; 2]);
    Ok(())
}
