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

/// Decodes a JPEG as the `image` crate does (the same decoder and colour conversion), but
/// in strict mode: a truncated file, a corrupt Huffman stream or a marker where none may
/// be is an error naming the file, never a picture padded with grey.
fn decode_jpeg_strict(path: &Path, bytes: &[u8]) -> Result<image::DynamicImage> {
    use zune_core::bytestream::ZCursor;
    use zune_core::colorspace::ColorSpace;
    let side = MAX_IMAGE_SIDE as usize;
    let options = zune_core::options::DecoderOptions::default()
        .set_strict_mode(true)
        .set_max_width(side)
        .set_max_height(side);
    let mut d = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(bytes), options);
    let corrupt = |e: zune_jpeg::errors::DecodeErrors| {
        Error::image(
            path,
            format!("corrupt or truncated JPEG ({e}); it is not used: re-export or remove it"),
        )
    };
    d.decode_headers().map_err(corrupt)?;
    let out = match d.input_colorspace() {
        Some(cs @ (ColorSpace::RGB | ColorSpace::RGBA | ColorSpace::Luma | ColorSpace::LumaA)) => {
            cs
        }
        _ => ColorSpace::RGB,
    };
    d.set_options(d.options().jpeg_set_out_colorspace(out));
    let px = d.decode().map_err(corrupt)?;
    let (w, h) = d
        .dimensions()
        .ok_or_else(|| Error::image(path, "JPEG without dimensions"))?;
    let (w, h) = (w as u32, h as u32);
    let short = || Error::image(path, "the JPEG decoder returned fewer pixels than its size");
    Ok(match out {
        ColorSpace::Luma => image::DynamicImage::ImageLuma8(
            image::ImageBuffer::from_raw(w, h, px).ok_or_else(short)?,
        ),
        ColorSpace::LumaA => image::DynamicImage::ImageLumaA8(
            image::ImageBuffer::from_raw(w, h, px).ok_or_else(short)?,
        ),
        ColorSpace::RGBA => image::DynamicImage::ImageRgba8(
            image::ImageBuffer::from_raw(w, h, px).ok_or_else(short)?,
        ),
        _ => image::DynamicImage::ImageRgb8(
            image::ImageBuffer::from_raw(w, h, px).ok_or_else(short)?,
        ),
    })
}

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

    /// Decodes a PNG or JPEG file. Grey and RGBA images are converted to RGB. A damaged
    /// or truncated file is refused, JPEGs included (their decoder runs in strict mode:
    /// a lenient one fills what it cannot read with grey and carries on).
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
        let reader = image::ImageReader::new(std::io::Cursor::new(&bytes))
            .with_guessed_format()
            .map_err(|e| Error::image(path, format!("cannot read: {e}")))?;
        let img = match reader.format() {
            Some(image::ImageFormat::Jpeg) => decode_jpeg_strict(path, &bytes)?,
            _ => reader
                .decode()
                .map_err(|e| Error::image(path, format!("cannot decode: {e}")))?,
        };
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
    /// so pixel `i` of the result covers pixels `2i, 2i+1` exactly. An empty image stays
    /// empty.
    pub fn downsample2(&self) -> Self {
        if self.width == 0 || self.height == 0 {
            return Self::new(0, 0);
        }
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

    /// Bilinear upsampling by an integer `factor` to `width` x `height`: the inverse of
    /// `factor`-fold box downsampling's geometry (output pixel centre `x + 0.5` reads
    /// `(x + 0.5) / factor - 0.5` here), clamped at the borders. Renders made at a lower
    /// resolution are compared with full-resolution photographs this way.
    pub fn upsample(&self, factor: u32, width: u32, height: u32) -> Self {
        let mut out = Self::new(width, height);
        if self.width == 0 || self.height == 0 {
            return out;
        }
        let f = factor.max(1) as f32;
        let sw = self.width as usize;
        let coord = |x: u32, n: u32| -> (usize, usize, f32) {
            let u = ((x as f32 + 0.5) / f - 0.5).clamp(0.0, (n - 1) as f32);
            let i = (u.floor() as usize).min(n as usize - 1);
            let j = (i + 1).min(n as usize - 1);
            (i, j, u - i as f32)
        };
        for y in 0..height {
            let (y0, y1, fy) = coord(y, self.height);
            for x in 0..width {
                let (x0, x1, fx) = coord(x, self.width);
                let o = (y as usize * width as usize + x as usize) * 3;
                for c in 0..3 {
                    let at = |xx: usize, yy: usize| self.data[(yy * sw + xx) * 3 + c];
                    let top = at(x0, y0) * (1.0 - fx) + at(x1, y0) * fx;
                    let bottom = at(x0, y1) * (1.0 - fx) + at(x1, y1) * fx;
                    out.data[o + c] = top * (1.0 - fy) + bottom * fy;
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

    /// Writes one frame of a sequence as a PNG with fast compression (about twice the
    /// size, a fraction of the time), straight to `path`: for files inside a directory
    /// that is itself put in place atomically once complete (a staged output directory),
    /// so no temporary file or flush per frame is needed.
    pub fn save_frame_png(&self, path: &Path) -> Result<()> {
        let png = encode_rgb8_png(
            path,
            self.width,
            self.height,
            &self.to_rgb8(),
            image::codecs::png::CompressionType::Fast,
        )?;
        std::fs::write(path, png).map_err(|e| Error::io(path, e))
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
    let buf = encode_rgb8_png(
        path,
        width,
        height,
        rgb,
        image::codecs::png::CompressionType::Default,
    )?;
    write_atomic(path, &buf)
}

/// An 8-bit RGB buffer as PNG bytes (`path`: named in the error).
fn encode_rgb8_png(
    path: &Path,
    width: u32,
    height: u32,
    rgb: &[u8],
    compression: image::codecs::png::CompressionType,
) -> Result<Vec<u8>> {
    use image::codecs::png::{FilterType, PngEncoder};
    let mut buf = Vec::new();
    let enc = PngEncoder::new_with_quality(&mut buf, compression, FilterType::Adaptive);
    image::ImageEncoder::write_image(enc, rgb, width, height, image::ExtendedColorType::Rgb8)
        .map_err(|e| Error::image(path, format!("cannot encode PNG: {e}")))?;
    Ok(buf)
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

#[cfg(test)]
mod tests {
    use super::*;

    fn ramp(w: u32, h: u32) -> RgbImage {
        let mut im = RgbImage::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let i = (y * w + x) as usize * 3;
                im.data[i] = (x as f32 + 0.5) / w as f32;
                im.data[i + 1] = (y as f32 + 0.5) / h as f32;
                im.data[i + 2] = 0.25;
            }
        }
        im
    }

    #[test]
    fn both_png_writers_read_back_as_the_8_bit_image() {
        let dir = std::env::temp_dir().join(format!("ds-png-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("temp dir");
        let im = ramp(37, 21);
        let want = im.to_rgb8();
        let (a, b) = (dir.join("atomic.png"), dir.join("frame.png"));
        im.save_png(&a).expect("save_png");
        im.save_frame_png(&b).expect("save_frame_png");
        for p in [&a, &b] {
            let got = RgbImage::load(p).expect("load");
            assert_eq!((got.width, got.height), (37, 21));
            assert_eq!(got.to_rgb8(), want, "{}", p.display());
        }
        // Nothing but the two files (no temporary left behind).
        assert_eq!(std::fs::read_dir(&dir).expect("list").count(), 2);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn upsample_inverts_box_downsampling_of_a_linear_ramp() {
        // A linear ramp box-downsampled by 4 and upsampled back is the ramp again, away
        // from the borders (where the upsampling clamps).
        let im = ramp(64, 32);
        let small = im.downsample2().downsample2();
        let up = small.upsample(4, 64, 32);
        for y in 2..30 {
            for x in 2..62 {
                let (a, b) = (im.pixel(x, y), up.pixel(x, y));
                for c in 0..3 {
                    assert!((a[c] - b[c]).abs() < 1e-5, "({x}, {y}): {a:?} vs {b:?}");
                }
            }
        }
        // Factor 1 at the same size is the identity.
        assert_eq!(im.upsample(1, 64, 32), im);
    }
}
