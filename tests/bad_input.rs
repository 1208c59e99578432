//! The bad-input corpus (issues 2 and 7): malformed scenes of every format and impossible
//! options, each run through `deepstereo inspect` and `deepstereo sweep`. Every run must
//! exit non-zero without panicking or hanging, name the offending file (or option) and
//! the problem on stderr, and leave no output file behind.
//!
//! The summary table (case, command, exit code, the error line of stderr) is printed in
//! the test output and written straight to stdout (uncaptured), so that
//! `cargo test --release -p deepstereo-tests --test bad_input` shows it for the README.

use deepstereo_core::camera::Intrinsics;
use deepstereo_tests::*;
use glam::{DMat3, DVec3};
use serde_json::{json, Value};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Which valid scene a case starts from.
#[derive(Clone, Copy, Debug)]
enum Base {
    Llff,
    ColmapText,
    ColmapBin,
    Nerf,
    Middlebury,
    /// An empty directory.
    Empty,
}

/// The commands a case runs.
#[derive(Clone, Copy, PartialEq)]
enum Cmds {
    Both,
    SweepOnly,
}

type Mutate = Box<dyn Fn(&Path)>;

struct Case {
    name: &'static str,
    base: Base,
    mutate: Mutate,
    /// Extra arguments (both commands); `{dir}` is replaced by the scene directory.
    args: Vec<String>,
    cmds: Cmds,
    /// Substrings stderr must contain: the file (or option) and the problem.
    expect: Vec<&'static str>,
    /// The `--scene` argument relative to the case directory, when not the scene itself.
    scene_arg: Option<&'static str>,
}

fn case(
    name: &'static str,
    base: Base,
    mutate: impl Fn(&Path) + 'static,
    expect: &[&'static str],
) -> Case {
    Case {
        name,
        base,
        mutate: Box::new(mutate),
        args: Vec::new(),
        cmds: Cmds::Both,
        expect: expect.to_vec(),
        scene_arg: None,
    }
}

impl Case {
    fn args(mut self, a: &[&str]) -> Self {
        self.args = a.iter().map(|s| s.to_string()).collect();
        self
    }
    fn sweep_only(mut self) -> Self {
        self.cmds = Cmds::SweepOnly;
        self
    }
    fn scene(mut self, rel: &'static str) -> Self {
        self.scene_arg = Some(rel);
        self
    }
}

/// Four cameras of a forward-facing rig, 16x12 images.
fn cameras() -> Vec<NamedCamera> {
    let k = Intrinsics::pinhole(14.0, 14.0, 8.0, 6.0, 16, 12);
    let mut rng = Rng(99);
    (0..4)
        .map(|i| {
            let r = DMat3::from_rotation_y(rng.range(-0.05, 0.05))
                * DMat3::from_rotation_x(rng.range(-0.05, 0.05));
            let c = DVec3::new(0.2 * i as f64, rng.range(-0.1, 0.1), 0.0);
            NamedCamera {
                name: format!("img_{i:03}.png"),
                camera: deepstereo_core::camera::Camera {
                    intrinsics: k,
                    pose: deepstereo_core::camera::WorldToCamera::new_checked(r, -(r * c))
                        .expect("rotation"),
                    rolling_shutter: None,
                },
            }
        })
        .collect()
}

fn points() -> Vec<DVec3> {
    (0..8)
        .map(|i| DVec3::new(0.1 * i as f64 - 0.4, 0.05 * i as f64, 3.0 + 0.4 * i as f64))
        .collect()
}

fn write_base(base: Base, dir: &Path) -> Vec<String> {
    let cams = cameras();
    std::fs::create_dir_all(dir).expect("mkdir");
    match base {
        Base::Llff => write_llff(dir, &cams, (1.0, 20.0), false),
        Base::ColmapText => write_colmap_text(dir, &cams, &["PINHOLE"], &points()),
        Base::ColmapBin => write_colmap_bin(dir, &cams, &["PINHOLE"], &points()),
        Base::Nerf => write_nerf(dir, &cams, true, Some((1.0, 20.0))),
        Base::Middlebury => {
            write_middlebury(dir, &cams);
            return ["--near", "1", "--far", "20"].map(String::from).to_vec();
        }
        Base::Empty => {}
    }
    Vec::new()
}

// ---- mutation helpers -------------------------------------------------------------

fn edit_text(path: PathBuf, f: impl Fn(String) -> String) {
    let s = std::fs::read_to_string(&path).expect("read");
    std::fs::write(&path, f(s)).expect("write");
}

fn edit_bytes(path: PathBuf, f: impl Fn(&mut Vec<u8>)) {
    let mut b = std::fs::read(&path).expect("read");
    f(&mut b);
    std::fs::write(&path, b).expect("write");
}

fn edit_json(path: PathBuf, f: impl Fn(&mut Value)) {
    let mut v: Value = serde_json::from_slice(&std::fs::read(&path).expect("read")).expect("json");
    f(&mut v);
    std::fs::write(&path, serde_json::to_string_pretty(&v).expect("json")).expect("write");
}

/// Rewrites `poses_bounds.npy` from edited rows (`<f8`, `cols` columns).
fn edit_rows(dir: &Path, cols: usize, f: impl Fn(&mut Vec<f64>)) {
    let mut rows = llff_rows(&cameras(), (1.0, 20.0));
    f(&mut rows);
    let n = rows.len() / cols;
    deepstereo_core::scene::npy::write_npy_f64(&dir.join("poses_bounds.npy"), &[n, cols], &rows)
        .expect("npy");
}

/// An `.npy` file with the given header dict and data bytes.
fn npy_with_header(header: &str, data: &[u8]) -> Vec<u8> {
    let mut h = header.to_string();
    while !(10 + h.len() + 1).is_multiple_of(64) {
        h.push(' ');
    }
    h.push('\n');
    let mut b = b"\x93NUMPY\x01\x00".to_vec();
    b.extend((h.len() as u16).to_le_bytes());
    b.extend(h.as_bytes());
    b.extend_from_slice(data);
    b
}

/// Replaces line `n` (0-based, counting every line) of a text file.
fn edit_line(path: PathBuf, n: usize, f: impl Fn(&str) -> String) {
    edit_text(path, |s| {
        s.lines()
            .enumerate()
            .map(|(i, l)| if i == n { f(l) } else { l.to_string() })
            .collect::<Vec<_>>()
            .join("\n")
            + "\n"
    });
}

/// Replaces the `k`-th whitespace-separated token of a line.
fn set_token(line: &str, k: usize, value: &str) -> String {
    line.split_whitespace()
        .enumerate()
        .map(|(i, t)| if i == k { value } else { t })
        .collect::<Vec<_>>()
        .join(" ")
}

/// A FIFO at `path`: opening it for reading would block, so a case that points a scene
/// file at one proves, by not timing out, that the reader never opened it.
fn fifo(path: &Path) {
    let ok = std::process::Command::new("mkfifo")
        .arg(path)
        .status()
        .is_ok_and(|s| s.success());
    assert!(ok, "mkfifo {}", path.display());
}

/// A FIFO beside the scene directory, outside it: `<case>/outside.png`.
fn outside_fifo(scene: &Path) -> PathBuf {
    let p = scene.parent().expect("case dir").join("outside.png");
    fifo(&p);
    p
}

/// A JPEG of the base scene's size (16x12) cut 8 bytes into its entropy-coded data (its
/// headers intact), under a `.png` name.
fn truncated_jpeg(path: &Path) {
    let img = image::RgbImage::from_fn(16, 12, |x, y| {
        image::Rgb([(x * 15) as u8, (y * 20) as u8, 90])
    });
    let mut bytes = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, 90)
        .encode_image(&img)
        .expect("jpeg");
    let sos = bytes
        .windows(2)
        .position(|w| w == [0xff, 0xda])
        .expect("SOS marker");
    let header = u16::from_be_bytes([bytes[sos + 2], bytes[sos + 3]]) as usize;
    bytes.truncate(sos + 2 + header + 8);
    std::fs::write(path, bytes).expect("write");
}

fn cases() -> Vec<Case> {
    use Base::*;
    let img = |d: &Path, n: usize| d.join("images").join(format!("img_{n:03}.png"));
    vec![
        // ---- LLFF ----
        case(
            "llff: fewer pose rows than images",
            Llff,
            |d| edit_rows(d, 17, |r| r.truncate(3 * 17)),
            &["poses_bounds.npy", "3 poses", "4 images"],
        ),
        case(
            "llff: truncated npy",
            Llff,
            |d| edit_bytes(d.join("poses_bounds.npy"), |b| b.truncate(b.len() - 50)),
            &["poses_bounds.npy", "truncated"],
        ),
        case(
            "llff: garbage npy header",
            Llff,
            |d| {
                edit_bytes(d.join("poses_bounds.npy"), |b| {
                    b[10..40].copy_from_slice(&[b'#'; 30])
                })
            },
            &["poses_bounds.npy", "invalid .npy"],
        ),
        case(
            "llff: not an npy file",
            Llff,
            |d| std::fs::write(d.join("poses_bounds.npy"), b"hello, world").expect("write"),
            &["poses_bounds.npy", "magic"],
        ),
        case(
            "llff: npy header claims 2^62 rows",
            Llff,
            |d| {
                std::fs::write(d.join("poses_bounds.npy"), npy_with_header("{'descr': '<f8', 'fortran_order': False, 'shape': (4611686018427387904, 17), }", &[0; 64])).expect("write")
            },
            &["poses_bounds.npy", "overflows"],
        ),
        case(
            "llff: npy of 0 rows",
            Llff,
            |d| {
                std::fs::write(
                    d.join("poses_bounds.npy"),
                    npy_with_header(
                        "{'descr': '<f8', 'fortran_order': False, 'shape': (0, 17), }",
                        &[],
                    ),
                )
                .expect("write")
            },
            &["poses_bounds.npy", "0 rows"],
        ),
        case(
            "llff: npy of int64",
            Llff,
            |d| {
                std::fs::write(
                    d.join("poses_bounds.npy"),
                    npy_with_header(
                        "{'descr': '<i8', 'fortran_order': False, 'shape': (4, 17), }",
                        &[0; 544],
                    ),
                )
                .expect("write")
            },
            &["poses_bounds.npy", "'<i8' is not supported"],
        ),
        case(
            "llff: npy of 15 columns",
            Llff,
            |d| {
                edit_rows(d, 15, |r| {
                    *r = r.chunks(17).flat_map(|c| c[..15].to_vec()).collect()
                })
            },
            &["poses_bounds.npy", "17 columns"],
        ),
        case(
            "llff: NaN in a pose",
            Llff,
            |d| edit_rows(d, 17, |r| r[17 + 3] = f64::NAN),
            &["poses_bounds.npy", "row 1", "non-finite"],
        ),
        case(
            "llff: non-orthonormal rotation",
            Llff,
            |d| edit_rows(d, 17, |r| (0..3).for_each(|i| r[2 * 17 + 5 * i] *= 1.5)),
            &["poses_bounds.npy", "img_002.png", "not orthonormal"],
        ),
        case(
            "llff: near > far",
            Llff,
            |d| edit_rows(d, 17, |r| r[15] = 50.0),
            &["poses_bounds.npy", "row 0", "far must be greater"],
        ),
        case(
            "llff: image is garbage bytes",
            Llff,
            move |d| std::fs::write(img(d, 2), b"\x00garbage, not a PNG").expect("write"),
            &["img_002.png", "cannot read the image header"],
        ),
        case(
            "llff: truncated image (header intact)",
            Llff,
            move |d| edit_bytes(img(d, 1), |b| b.truncate(60)),
            &["img_001.png", "cannot decode"],
        )
        .sweep_only(),
        case(
            "llff: image of the wrong size",
            Llff,
            move |d| write_png(&img(d, 3), 20, 12, 5),
            &["img_003.png", "20x12", "16x12"],
        ),
        case(
            "llff: first image claims 10^9 x 12",
            Llff,
            move |d| {
                std::fs::write(img(d, 0), png_without_pixels(1_000_000_000, 12)).expect("write")
            },
            &["img_000.png", "1000000000"],
        ),
        case(
            "llff: no image folder",
            Llff,
            |d| std::fs::remove_dir_all(d.join("images")).expect("rm"),
            &["images", "no images/"],
        ),
        case(
            "llff: empty image folder",
            Llff,
            |d| {
                std::fs::remove_dir_all(d.join("images")).expect("rm");
                std::fs::create_dir(d.join("images")).expect("mkdir");
            },
            &["poses_bounds.npy", "0 images"],
        ),
        case(
            "llff: --factor of a missing folder",
            Llff,
            |_| {},
            &["images_8", "does not exist"],
        )
        .args(&["--factor", "8"]),
        // ---- COLMAP text ----
        case(
            "colmap txt: wrong parameter count",
            ColmapText,
            |d| {
                edit_line(d.join("sparse/0/cameras.txt"), 2, |l| {
                    l.rsplit_once(' ')
                        .map(|(a, _)| a.to_string())
                        .unwrap_or_default()
                })
            },
            &["cameras.txt:3", "needs 4 parameters"],
        ),
        case(
            "colmap txt: unknown camera model",
            ColmapText,
            |d| {
                edit_line(d.join("sparse/0/cameras.txt"), 1, |l| {
                    set_token(l, 1, "FISHEYE_DELUXE")
                })
            },
            &["cameras.txt:2", "unsupported camera model FISHEYE_DELUXE"],
        ),
        case(
            "colmap txt: image uses a missing camera",
            ColmapText,
            |d| edit_line(d.join("sparse/0/images.txt"), 3, |l| set_token(l, 8, "99")),
            &["images.txt", "camera 99"],
        ),
        case(
            "colmap txt: truncated image record",
            ColmapText,
            |d| {
                edit_line(d.join("sparse/0/images.txt"), 5, |l| {
                    l.split_whitespace().take(5).collect::<Vec<_>>().join(" ")
                })
            },
            &["images.txt:6", "missing pose value 5"],
        ),
        case(
            "colmap txt: non-UTF-8",
            ColmapText,
            |d| {
                edit_bytes(d.join("sparse/0/cameras.txt"), |b| {
                    b.splice(40..40, [0xff, 0xfe, 0xc3]).for_each(drop)
                })
            },
            &["cameras.txt", "UTF-8"],
        ),
        case(
            "colmap txt: width 10^9",
            ColmapText,
            |d| {
                edit_line(d.join("sparse/0/cameras.txt"), 1, |l| {
                    set_token(l, 2, "1000000000")
                })
            },
            &["cameras.txt:2", "1000000000"],
        ),
        case(
            "colmap txt: NaN quaternion",
            ColmapText,
            |d| edit_line(d.join("sparse/0/images.txt"), 1, |l| set_token(l, 1, "nan")),
            &["images.txt", "img_000.png", "quaternion"],
        ),
        case(
            "colmap txt: missing image file",
            ColmapText,
            move |d| std::fs::remove_file(img(d, 2)).expect("rm"),
            &["img_002.png", "not found"],
        ),
        case(
            "colmap txt: image listed twice",
            ColmapText,
            |d| {
                edit_line(d.join("sparse/0/images.txt"), 3, |l| {
                    set_token(l, 9, "img_000.png")
                })
            },
            &["images.txt", "img_000.png", "twice"],
        ),
        case(
            "colmap txt: bad point",
            ColmapText,
            |d| edit_line(d.join("sparse/0/points3D.txt"), 2, |l| set_token(l, 2, "x")),
            &["points3D.txt:3", "bad Y 'x'"],
        ),
        case(
            "colmap txt: no images",
            ColmapText,
            |d| std::fs::write(d.join("sparse/0/images.txt"), "# nothing\n").expect("write"),
            &["scene", "no views"],
        ),
        // ---- COLMAP binary ----
        case(
            "colmap bin: image count too large",
            ColmapBin,
            |d| {
                edit_bytes(d.join("sparse/0/images.bin"), |b| {
                    b[..8].copy_from_slice(&1000u64.to_le_bytes())
                })
            },
            &["images.bin", "image count 1000"],
        ),
        case(
            "colmap bin: image count too small",
            ColmapBin,
            |d| {
                edit_bytes(d.join("sparse/0/images.bin"), |b| {
                    b[..8].copy_from_slice(&3u64.to_le_bytes())
                })
            },
            &["images.bin", "trailing bytes"],
        ),
        case(
            "colmap bin: camera count 2^64-1",
            ColmapBin,
            |d| {
                edit_bytes(d.join("sparse/0/cameras.bin"), |b| {
                    b[..8].copy_from_slice(&u64::MAX.to_le_bytes())
                })
            },
            &["cameras.bin", "camera count"],
        ),
        case(
            "colmap bin: truncated cameras",
            ColmapBin,
            |d| edit_bytes(d.join("sparse/0/cameras.bin"), |b| b.truncate(b.len() - 5)),
            &["cameras.bin", "truncated"],
        ),
        case(
            "colmap bin: truncated images",
            ColmapBin,
            |d| edit_bytes(d.join("sparse/0/images.bin"), |b| b.truncate(b.len() / 2)),
            &["images.bin", "truncated"],
        ),
        case(
            "colmap bin: unknown camera model id",
            ColmapBin,
            |d| {
                edit_bytes(d.join("sparse/0/cameras.bin"), |b| {
                    b[12..16].copy_from_slice(&42i32.to_le_bytes())
                })
            },
            &["cameras.bin", "model id 42"],
        ),
        case(
            "colmap bin: unsupported model (fisheye)",
            ColmapBin,
            |d| {
                edit_bytes(d.join("sparse/0/cameras.bin"), |b| {
                    b[12..16].copy_from_slice(&5i32.to_le_bytes())
                })
            },
            &["cameras.bin", "unsupported camera model OPENCV_FISHEYE"],
        ),
        case(
            "colmap bin: width 10^9",
            ColmapBin,
            |d| {
                edit_bytes(d.join("sparse/0/cameras.bin"), |b| {
                    b[16..24].copy_from_slice(&1_000_000_000u64.to_le_bytes())
                })
            },
            &["cameras.bin", "1000000000"],
        ),
        case(
            "colmap bin: truncated points3D",
            ColmapBin,
            |d| edit_bytes(d.join("sparse/0/points3D.bin"), |b| b.truncate(b.len() - 3)),
            &["points3D.bin", "truncated"],
        ),
        // ---- NeRF ----
        case(
            "nerf: truncated JSON",
            Nerf,
            |d| edit_bytes(d.join("transforms.json"), |b| b.truncate(b.len() / 2)),
            &["transforms.json", "invalid JSON"],
        ),
        case(
            "nerf: non-UTF-8",
            Nerf,
            |d| {
                edit_bytes(d.join("transforms.json"), |b| {
                    b.splice(3..3, [0xff, 0xfe]).for_each(drop)
                })
            },
            &["transforms.json", "invalid JSON"],
        ),
        case(
            "nerf: missing frames",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    drop(v.as_object_mut().map(|o| o.remove("frames")))
                })
            },
            &["transforms.json", "missing 'frames'"],
        ),
        case(
            "nerf: frames not an array",
            Nerf,
            |d| edit_json(d.join("transforms.json"), |v| v["frames"] = json!({"a": 1})),
            &["transforms.json", "'frames' must be an array"],
        ),
        case(
            "nerf: no focal length",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    drop(
                        v.as_object_mut()
                            .map(|o| (o.remove("fl_x"), o.remove("fl_y"))),
                    )
                })
            },
            &["transforms.json", "frame 0", "no focal length"],
        ),
        case(
            "nerf: fl_x is a string",
            Nerf,
            |d| edit_json(d.join("transforms.json"), |v| v["fl_x"] = json!("big")),
            &["transforms.json", "'fl_x' must be a finite number"],
        ),
        case(
            "nerf: missing transform_matrix",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    drop(
                        v["frames"][1]
                            .as_object_mut()
                            .map(|o| o.remove("transform_matrix")),
                    )
                })
            },
            &["transforms.json", "frame 1", "missing 'transform_matrix'"],
        ),
        case(
            "nerf: transform_matrix wrong type",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    v["frames"][2]["transform_matrix"] = json!("identity")
                })
            },
            &["transforms.json", "frame 2", "'transform_matrix' must be"],
        ),
        case(
            "nerf: transform_matrix 3x3",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    v["frames"][0]["transform_matrix"] = json!([[1, 0, 0], [0, 1, 0], [0, 0, 1]])
                })
            },
            &["transforms.json", "frame 0", "'transform_matrix' must be"],
        ),
        case(
            "nerf: non-orthonormal rotation",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    v["frames"][3]["transform_matrix"][0][0] = json!(3.0)
                })
            },
            &["transforms.json", "not orthonormal"],
        ),
        case(
            "nerf: transform_matrix_end malformed",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    v["frames"][1]["transform_matrix_end"] = json!([[1, 0, 0, 0], [0, 1, 0]])
                })
            },
            &[
                "transforms.json",
                "frame 1",
                "'transform_matrix_end' must be",
            ],
        ),
        case(
            "nerf: transform_matrix_end not a rotation",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    let mut m = v["frames"][2]["transform_matrix"].clone();
                    m[1][1] = json!(4.0);
                    v["frames"][2]["transform_matrix_end"] = m;
                })
            },
            &[
                "transforms.json",
                "'transform_matrix_end'",
                "not orthonormal",
            ],
        ),
        case(
            "nerf: rolling_shutter non-finite",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    v["frames"][0]["rolling_shutter"] = json!([0.0, "nan", 1.0, 0.0])
                })
            },
            &[
                "transforms.json",
                "frame 0",
                "'rolling_shutter' must be an array of 3 or 4 finite numbers",
            ],
        ),
        case(
            "nerf: rolling_shutter too short",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    v["rolling_shutter"] = json!([0.0, 1.0])
                })
            },
            &[
                "transforms.json",
                "'rolling_shutter' must be an array of 3 or 4",
            ],
        ),
        case(
            "nerf: missing image",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    v["frames"][1]["file_path"] = json!("images/nope.png")
                })
            },
            &["nope.png", "not found"],
        ),
        case(
            "nerf: file_path is a number",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    v["frames"][1]["file_path"] = json!(5)
                })
            },
            &["transforms.json", "frame 1", "'file_path' must be"],
        ),
        case(
            "nerf: w = 10^9",
            Nerf,
            |d| edit_json(d.join("transforms.json"), |v| v["w"] = json!(1e9)),
            &["transforms.json", "'w' must be a positive whole number"],
        ),
        case(
            "nerf: h = -5",
            Nerf,
            |d| edit_json(d.join("transforms.json"), |v| v["h"] = json!(-5)),
            &["transforms.json", "'h' must be"],
        ),
        case(
            "nerf: top level is an array",
            Nerf,
            |d| std::fs::write(d.join("transforms.json"), "[1, 2]").expect("write"),
            &["transforms.json", "must be an object"],
        ),
        case(
            "nerf: camera_angle_x = 4 rad",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    drop(
                        v.as_object_mut()
                            .map(|o| (o.remove("fl_x"), o.remove("fl_y"))),
                    );
                    v["camera_angle_x"] = json!(4.0);
                })
            },
            &["transforms.json", "'camera_angle_x' must be an angle"],
        ),
        case(
            "nerf: near without far",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    drop(v.as_object_mut().map(|o| o.remove("far")))
                })
            },
            &["transforms.json", "'near' and 'far'"],
        ),
        // ---- Middlebury ----
        case(
            "middlebury: count mismatch",
            Middlebury,
            |d| edit_line(d.join("scene_par.txt"), 0, |_| "5".into()),
            &["scene_par.txt:1", "says 5 views"],
        ),
        case(
            "middlebury: short line",
            Middlebury,
            |d| {
                edit_line(d.join("scene_par.txt"), 2, |l| {
                    l.split_whitespace().take(12).collect::<Vec<_>>().join(" ")
                })
            },
            &["scene_par.txt:3", "21 numbers"],
        ),
        case(
            "middlebury: not a number",
            Middlebury,
            |d| edit_line(d.join("scene_par.txt"), 1, |l| set_token(l, 4, "abc")),
            &["scene_par.txt:2", "'abc' is not a number"],
        ),
        case(
            "middlebury: NaN",
            Middlebury,
            |d| edit_line(d.join("scene_par.txt"), 1, |l| set_token(l, 19, "nan")),
            &["scene_par.txt:2", "non-finite"],
        ),
        case(
            "middlebury: non-orthonormal rotation",
            Middlebury,
            |d| edit_line(d.join("scene_par.txt"), 3, |l| set_token(l, 10, "2.5")),
            &["scene_par.txt", "img_002.png", "not orthonormal"],
        ),
        case(
            "middlebury: skewed K",
            Middlebury,
            |d| edit_line(d.join("scene_par.txt"), 1, |l| set_token(l, 2, "0.5")),
            &["scene_par.txt:2", "skew"],
        ),
        case(
            "middlebury: non-UTF-8",
            Middlebury,
            |d| {
                edit_bytes(d.join("scene_par.txt"), |b| {
                    b.splice(2..2, [0xff]).for_each(drop)
                })
            },
            &["scene_par.txt", "UTF-8"],
        ),
        case(
            "middlebury: missing image",
            Middlebury,
            |d| std::fs::remove_file(d.join("img_001.png")).expect("rm"),
            &["img_001.png"],
        ),
        case(
            "middlebury: image claims 10^9 x 12",
            Middlebury,
            |d| {
                std::fs::write(d.join("img_000.png"), png_without_pixels(1_000_000_000, 12))
                    .expect("write")
            },
            &["img_000.png", "1000000000"],
        ),
        case(
            "middlebury: empty file",
            Middlebury,
            |d| std::fs::write(d.join("scene_par.txt"), "").expect("write"),
            &["scene_par.txt", "empty file"],
        ),
        // ---- paths outside the scene: refused unread (a FIFO would hang the reader) ----
        case(
            "outside: nerf file_path ../outside.png (a FIFO)",
            Nerf,
            |d| {
                outside_fifo(d);
                edit_json(d.join("transforms.json"), |v| {
                    v["frames"][1]["file_path"] = json!("../outside.png")
                })
            },
            &[
                "transforms.json",
                "frame 1",
                "outside the scene directory",
                "--allow-outside-paths",
            ],
        ),
        case(
            "outside: nerf file_path absolute (a FIFO)",
            Nerf,
            |d| {
                let p = outside_fifo(d);
                edit_json(d.join("transforms.json"), |v| {
                    v["frames"][0]["file_path"] = json!(p.to_string_lossy())
                })
            },
            &["transforms.json", "frame 0", "outside the scene directory"],
        ),
        case(
            "outside: nerf file_path ../../../../etc/passwd",
            Nerf,
            |d| {
                edit_json(d.join("transforms.json"), |v| {
                    v["frames"][2]["file_path"] = json!("../../../../../../../../etc/passwd")
                })
            },
            &["transforms.json", "frame 2", "outside the scene directory"],
        ),
        case(
            "outside: nerf image a symbolic link to a FIFO outside",
            Nerf,
            move |d| {
                let p = outside_fifo(d);
                std::fs::remove_file(img(d, 3)).expect("rm");
                std::os::unix::fs::symlink(p, img(d, 3)).expect("symlink");
            },
            &["transforms.json", "frame 3", "outside the scene directory"],
        ),
        case(
            "outside: colmap text image ../outside.png",
            ColmapText,
            |d| {
                outside_fifo(d);
                edit_text(d.join("sparse/0/images.txt"), |s| {
                    s.replace("img_001.png", "../../outside.png")
                })
            },
            &[
                "images.txt",
                "line 4",
                "../../outside.png",
                "outside the scene directory",
            ],
        ),
        case(
            "outside: colmap bin image ../outsideX",
            ColmapBin,
            |d| {
                fifo(&d.parent().expect("case").join("outsideX"));
                edit_bytes(d.join("sparse/0/images.bin"), |b| {
                    let at = b
                        .windows(11)
                        .position(|w| w == b"img_002.png")
                        .expect("name");
                    b[at..at + 11].copy_from_slice(b"../outsideX");
                })
            },
            &["images.bin", "../outsideX", "outside the scene directory"],
        ),
        case(
            "outside: middlebury image ../outside.png",
            Middlebury,
            |d| {
                outside_fifo(d);
                edit_line(d.join("scene_par.txt"), 2, |l| {
                    l.replacen("img_001.png", "../outside.png", 1)
                })
            },
            &["scene_par.txt", "line 3", "outside the scene directory"],
        ),
        case(
            "outside: llff image a symbolic link to a FIFO outside",
            Llff,
            move |d| {
                let p = outside_fifo(d);
                std::fs::remove_file(img(d, 2)).expect("rm");
                std::os::unix::fs::symlink(p, img(d, 2)).expect("symlink");
            },
            &["images", "img_002.png", "outside the scene directory"],
        ),
        case(
            "outside: llff poses_bounds.npy a link outside",
            Llff,
            |d| {
                let p = d.parent().expect("case").join("poses.npy");
                std::fs::rename(d.join("poses_bounds.npy"), &p).expect("mv");
                std::os::unix::fs::symlink(p, d.join("poses_bounds.npy")).expect("symlink");
            },
            &["poses_bounds.npy", "outside the scene directory"],
        ),
        case(
            "llff: poses_bounds.npy is a FIFO",
            Llff,
            |d| {
                std::fs::remove_file(d.join("poses_bounds.npy")).expect("rm");
                fifo(&d.join("poses_bounds.npy"));
            },
            &["poses_bounds.npy", "not a regular file"],
        ),
        // ---- corrupt images, absurd cameras, duplicate ids ----
        case(
            "llff: truncated JPEG (header intact)",
            Llff,
            move |d| truncated_jpeg(&img(d, 1)),
            &["img_001.png", "corrupt or truncated JPEG"],
        )
        .sweep_only(),
        case(
            "colmap text: zero focal length in cameras.txt",
            ColmapText,
            |d| edit_line(d.join("sparse/0/cameras.txt"), 2, |l| set_token(l, 4, "0")),
            &[
                "cameras.txt:3",
                "camera 2",
                "focal lengths must be positive",
            ],
        ),
        case(
            "colmap text: duplicate image id",
            ColmapText,
            |d| edit_line(d.join("sparse/0/images.txt"), 3, |l| set_token(l, 0, "1")),
            &["images.txt:4", "image id 1 appears twice"],
        ),
        case(
            "colmap bin: duplicate image id",
            ColmapBin,
            |d| {
                edit_bytes(d.join("sparse/0/images.bin"), |b| {
                    let at = b
                        .windows(11)
                        .position(|w| w == b"img_001.png")
                        .expect("name");
                    // The record before the name: id u32, 7 f64, camera id u32.
                    let id = at - 4 - 56 - 4;
                    b[id..id + 4].copy_from_slice(&1u32.to_le_bytes());
                })
            },
            &["images.bin", "image id 1 appears twice"],
        ),
        case(
            "nerf: fl_x = 1e300",
            Nerf,
            |d| edit_json(d.join("transforms.json"), |v| v["fl_x"] = json!(1e300)),
            &[
                "transforms.json",
                "focal length",
                "times the image's larger side",
            ],
        ),
        case(
            "nerf: principal point 10^6 px away",
            Nerf,
            |d| edit_json(d.join("transforms.json"), |v| v["cx"] = json!(1e6)),
            &["transforms.json", "principal point"],
        ),
        // ---- any scene ----
        case("empty directory", Empty, |_| {}, &["unknown scene format"]),
        case(
            "directory of unrelated files",
            Empty,
            |d| std::fs::write(d.join("notes.txt"), "hello").expect("write"),
            &["unknown scene format"],
        ),
        case(
            "scene path is a file",
            Empty,
            |d| std::fs::write(d.join("file"), "x").expect("write"),
            &["file", "not a directory"],
        )
        .scene("file"),
        case(
            "scene path does not exist",
            Empty,
            |_| {},
            &["missing", "not a directory"],
        )
        .scene("missing"),
        case("--format bogus", Llff, |_| {}, &["--format", "bogus"]).args(&["--format", "bogus"]),
        case(
            "--format colmap on an LLFF scene",
            Llff,
            |_| {},
            &["no COLMAP model"],
        )
        .args(&["--format", "colmap"]),
        case(
            "--near -1",
            Llff,
            |_| {},
            &["near must be finite and positive", "-1"],
        )
        .args(&["--near=-1", "--far", "10"]),
        case(
            "--near NaN",
            Llff,
            |_| {},
            &["near must be finite and positive", "NaN"],
        )
        .args(&["--near", "NaN", "--far", "10"]),
        case(
            "--far <= --near",
            Llff,
            |_| {},
            &["far must be greater than near"],
        )
        .args(&["--near", "5", "--far", "2"]),
        case(
            "--far NaN",
            Llff,
            |_| {},
            &["far must be greater than near"],
        )
        .args(&["--far", "NaN"]),
        case(
            "--near 0",
            Llff,
            |_| {},
            &["near must be finite and positive"],
        )
        .args(&["--near", "0"]),
        case(
            "--target out of range",
            Llff,
            |_| {},
            &["--target 99", "out of range"],
        )
        .args(&["--target", "99"])
        .sweep_only(),
        case("--planes 0", Llff, |_| {}, &["--planes"])
            .args(&["--planes", "0"])
            .sweep_only(),
        case(
            "--planes 10^11",
            Llff,
            |_| {},
            &["100000000000 planes", "cannot be allocated"],
        )
        .args(&["--planes", "100000000000"])
        .sweep_only(),
        case("--planes 2^63", Llff, |_| {}, &["planes", "overflows"])
            .args(&["--planes", "9223372036854775807"])
            .sweep_only(),
        case("--target -1", Llff, |_| {}, &["--target", "-1"])
            .args(&["--target=-1"])
            .sweep_only(),
        case("--views 0", Llff, |_| {}, &["--views"])
            .args(&["--views", "0"])
            .sweep_only(),
    ]
}

/// Runs one command of a case; returns the table row and any failure.
fn run_case(c: &Case, index: usize, root: &Path, cmd: &str) -> (String, Option<String>) {
    let case_dir = root.join(format!("case_{index:02}_{cmd}"));
    let scene = case_dir.join("scene");
    std::fs::create_dir_all(&scene).expect("mkdir");
    let mut args_base = write_base(c.base, &scene);
    (c.mutate)(&scene);
    let scene_arg = c
        .scene_arg
        .map(|r| scene.join(r))
        .unwrap_or_else(|| scene.clone());
    let out = case_dir.join("out.safetensors");
    let mut args: Vec<String> = vec![
        cmd.into(),
        "--scene".into(),
        scene_arg.to_string_lossy().into_owned(),
    ];
    if c.args
        .iter()
        .any(|a| a.starts_with("--near") || a.starts_with("--far"))
    {
        args_base.clear();
    }
    args.extend(args_base);
    if cmd == "sweep" {
        let overrides: Vec<&str> = c.args.iter().map(String::as_str).collect();
        for (opt, val) in [("--target", "0"), ("--views", "2"), ("--planes", "3")] {
            let given = overrides
                .iter()
                .any(|a| *a == opt || a.starts_with(&format!("{opt}=")));
            if !given {
                args.extend([opt.to_string(), val.to_string()]);
            }
        }
        args.extend(["--out".to_string(), out.to_string_lossy().into_owned()]);
    }
    args.extend(c.args.iter().cloned());
    let res = run_deepstereo(&args);
    let line = res
        .stderr
        .lines()
        .find(|l| l.starts_with("error"))
        .unwrap_or_else(|| res.first_stderr_line())
        .replace(&*root.to_string_lossy(), "<tmp>");
    let code = res.code.map_or("killed".to_string(), |c| c.to_string());
    let row = format!(
        "| {} | {cmd} | {code} | `{}` |",
        c.name,
        line.replace('|', "\\|")
    );
    let mut problems = Vec::new();
    if res.timed_out {
        problems.push("timed out (hang)".to_string());
    }
    if res.code == Some(0) || res.code.is_none() {
        problems.push(format!(
            "exit code {:?}, expected a non-zero exit",
            res.code
        ));
    }
    if res.code == Some(101) || res.stderr.contains("panicked") {
        problems.push("panicked".to_string());
    }
    for e in &c.expect {
        if !res.stderr.contains(e) {
            problems.push(format!("stderr lacks {e:?}"));
        }
    }
    if out.exists() {
        problems.push("left an output file".to_string());
    }
    let failure = (!problems.is_empty()).then(|| {
        format!(
            "{} [{cmd}]: {}\n  args: {args:?}\n  stderr: {}",
            c.name,
            problems.join("; "),
            res.stderr.trim()
        )
    });
    std::fs::remove_dir_all(&case_dir).ok();
    (row, failure)
}

#[test]
fn valid_base_scenes_work() {
    let tmp = tempfile::tempdir().expect("tempdir");
    for base in [
        Base::Llff,
        Base::ColmapText,
        Base::ColmapBin,
        Base::Nerf,
        Base::Middlebury,
    ] {
        let scene = tmp.path().join(format!("{base:?}"));
        let extra = write_base(base, &scene);
        for cmd in ["inspect", "sweep"] {
            let out = tmp.path().join(format!("{base:?}.safetensors"));
            let mut args: Vec<String> = vec![
                cmd.into(),
                "--scene".into(),
                scene.to_string_lossy().into_owned(),
            ];
            args.extend(extra.iter().cloned());
            if cmd == "sweep" {
                args.extend(
                    ["--target", "0", "--views", "2", "--planes", "3", "--out"].map(String::from),
                );
                args.push(out.to_string_lossy().into_owned());
            }
            let res = run_deepstereo(&args);
            assert_eq!(res.code, Some(0), "{base:?} {cmd}: {}", res.stderr);
            if cmd == "sweep" {
                assert!(out.is_file());
            }
        }
    }
}

#[test]
fn bad_input_corpus() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let mut rows = vec![
        "| case | command | exit | error line of stderr |".to_string(),
        "|---|---|---|---|".to_string(),
    ];
    let mut failures = Vec::new();
    let cases = cases();
    for (i, c) in cases.iter().enumerate() {
        let cmds: &[&str] = match c.cmds {
            Cmds::Both => &["inspect", "sweep"],
            Cmds::SweepOnly => &["sweep"],
        };
        for cmd in cmds {
            let (row, failure) = run_case(c, i, tmp.path(), cmd);
            rows.push(row);
            failures.extend(failure);
        }
    }
    let table = rows.join("\n");
    let summary = format!(
        "\nbad-input corpus: {} cases, {} runs, {} failures\n{table}\n",
        cases.len(),
        rows.len() - 2,
        failures.len()
    );
    println!("{summary}");
    let _ = std::io::stdout().write_all(summary.as_bytes());
    assert!(
        failures.is_empty(),
        "{} failures:\n{}",
        failures.len(),
        failures.join("\n\n")
    );
}
