//! Images as f32 RGB in [0, 1], interleaved `[H, W, 3]`, plus the box-filter pyramid the
//! multi-resolution plane sweep samples from, and atomic PNG writing.

use crate::error::{Error, Result};
use std::io::Write;
use std::path::Path;

/// An RGB image with colours in [0, 1], stored row-major interleaved `[H, W, 3]`.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

/// Largest accepted image side, so that a corrupt header cannot request a huge allocation.
pub const MAX_IMAGE_SIDE: u32 = 32_768;

impl RgbImage {
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            data: vec![0.0; width as usize * height as usize * 3],
        }
    }

    #[inline]
    pub fn pixel(&self, x: u32, y: u32) -> [f32; 3] {
        let i = (y as usize * self.width as usize + x as usize) * 3;
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }

    /// Decodes a PNG or JPEG file. Grey and RGBA images are converted to RGB.
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
        let reader = image::ImageReader::new(std::io::Cursor::new(&bytes))
            .with_guessed_format()
            .map_err(|e| Error::image(path, format!("cannot read: {e}")))?;
        let (w, h) = reader
            .into_dimensions()
            .map_err(|e| Error::image(path, format!("cannot decode header: {e}")))?;
        if w == 0 || h == 0 || w > MAX_IMAGE_SIDE || h > MAX_IMAGE_SIDE {
            return Err(Error::image(
                path,
                format!("unsupported image size {w}x{h}"),
            ));
        }
        let img = image::ImageReader::new(std::io::Cursor::new(&bytes))
            .with_guessed_format()
            .map_err(|e| Error::image(path, format!("cannot read: {e}")))?
            .decode()
            .map_err(|e| Error::image(path, format!("cannot decode: {e}")))?;
        let rgb = img.to_rgb32f();
        let data = rgb.into_raw();
        if data.iter().any(|v| !v.is_finite()) {
            return Err(Error::image(path, "image contains non-finite values"));
        }
        Ok(Self {
            width: w,
            height: h,
            data: data.into_iter().map(|v| v.clamp(0.0, 1.0)).collect(),
        })
    }

    /// Loads and checks the size against what the camera expects.
    pub fn load_expecting(path: &Path, width: u32, height: u32) -> Result<Self> {
        let img = Self::load(path)?;
        if img.width != width || img.height != height {
            return Err(Error::image(
                path,
                format!(
                    "image is {}x{} but its camera expects {width}x{height}",
                    img.width, img.height
                ),
            ));
        }
        Ok(img)
    }

    /// Halves the resolution with a 2x2 box filter; an odd last row or column is dropped,
    /// so pixel `i` of the result covers pixels `2i, 2i+1` exactly.
    pub fn downsample2(&self) -> Self {
        let (w, h) = ((self.width / 2).max(1), (self.height / 2).max(1));
        let mut out = Self::new(w, h);
        let sw = self.width as usize;
        for y in 0..h as usize {
            for x in 0..w as usize {
                for c in 0..3 {
                    let mut acc = 0.0;
                    let mut n = 0.0;
                    for dy in 0..2 {
                        for dx in 0..2 {
                            let (xx, yy) = (2 * x + dx, 2 * y + dy);
                            if xx < sw && yy < self.height as usize {
                                acc += self.data[(yy * sw + xx) * 3 + c];
                                n += 1.0;
                            }
                        }
                    }
                    out.data[(y * w as usize + x) * 3 + c] = acc / n;
                }
            }
        }
        out
    }

    /// Levels `0..levels` of the box pyramid (level 0 is a copy of `self`).
    pub fn pyramid(&self, levels: usize) -> Vec<RgbImage> {
        let mut out = vec![self.clone()];
        for _ in 1..levels {
            let next = out[out.len() - 1].downsample2();
            out.push(next);
        }
        out
    }

    /// 8-bit RGB buffer (values clamped to [0, 1], non-finite written as 0).
    pub fn to_rgb8(&self) -> Vec<u8> {
        self.data
            .iter()
            .map(|&v| {
                let v = if v.is_finite() {
                    v.clamp(0.0, 1.0)
                } else {
                    0.0
                };
                (v * 255.0 + 0.5) as u8
            })
            .collect()
    }

    /// Writes a PNG atomically.
    pub fn save_png(&self, path: &Path) -> Result<()> {
        save_rgb8_png(path, self.width, self.height, &self.to_rgb8())
    }
}

/// Writes `bytes` to `path` atomically: a temporary file in the same directory, then rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty());
    if let Some(dir) = dir {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    let file_name = path
        .file_name()
        .ok_or_else(|| Error::Invalid(format!("{}: not a file path", path.display())))?;
    let tmp = path.with_file_name(format!(
        ".{}.{}.tmp",
        file_name.to_string_lossy(),
        std::process::id()
    ));
    let result = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(Error::io(path, e));
    }
    Ok(())
}

/// Encodes an 8-bit RGB buffer as PNG and writes it atomically.
pub fn save_rgb8_png(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<()> {
    let mut buf = Vec::new();
    let enc = image::codecs::png::PngEncoder::new(&mut buf);
    image::ImageEncoder::write_image(enc, rgb, width, height, image::ExtendedColorType::Rgb8)
        .map_err(|e| Error::image(path, format!("cannot encode PNG: {e}")))?;
    write_atomic(path, &buf)
}

/// Encodes a 16-bit greyscale buffer as PNG and writes it atomically.
pub fn save_gray16_png(path: &Path, width: u32, height: u32, values: &[u16]) -> Result<()> {
    let mut bytes = Vec::with_capacity(values.len() * 2);
    for v in values {
        bytes.extend_from_slice(&v.to_ne_bytes());
    }
    let mut buf = Vec::new();
    let enc = image::codecs::png::PngEncoder::new(&mut buf);
    image::ImageEncoder::write_image(enc, &bytes, width, height, image::ExtendedColorType::L16)
        .map_err(|e| Error::image(path, format!("cannot encode PNG: {e}")))?;
    write_atomic(path, &buf)
}
