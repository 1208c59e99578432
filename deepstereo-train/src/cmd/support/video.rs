//! Camera-path videos: H.264 MP4 through `ffmpeg` when it is on the PATH (raw RGB frames
//! piped to it, padded to even dimensions, `yuv420p`), else an animated GIF written
//! natively. Written atomically: a temporary file beside the output, then a rename.

use anyhow::{bail, Context, Result};
use deepstereo_core::imageio::RgbImage;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// Frames per second when `--fps` is not given.
pub const DEFAULT_FPS: f64 = 24.0;
/// The environment variable naming the ffmpeg binary (default `ffmpeg`; a name that does
/// not run makes videos fall back to GIF).
pub const FFMPEG_ENV: &str = "DEEPSTEREO_FFMPEG";
/// GIF colour quantisation speed (1 best, 30 fastest).
const GIF_SPEED: i32 = 10;
/// ffmpeg's constant rate factor for H.264 (lower is better quality).
const H264_CRF: &str = "18";

/// What was written.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Video {
    Mp4(PathBuf),
    Gif(PathBuf),
}

impl Video {
    pub fn path(&self) -> &Path {
        match self {
            Video::Mp4(p) | Video::Gif(p) => p,
        }
    }
}

/// The ffmpeg binary to run, if it runs.
pub fn ffmpeg() -> Option<String> {
    let prog = std::env::var(FFMPEG_ENV).unwrap_or_else(|_| "ffmpeg".to_string());
    let ok = Command::new(&prog)
        .arg("-version")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .map(|s| s.success())
        .unwrap_or(false);
    ok.then_some(prog)
}

/// Checks the options before any frame is rendered.
pub fn check(out: &Path, fps: f64) -> Result<()> {
    if !(fps.is_finite() && fps > 0.0 && fps <= 240.0) {
        bail!("--fps {fps}: must be in (0, 240]");
    }
    if out.file_name().is_none() {
        bail!("--video {}: not a file path", out.display());
    }
    if out.is_dir() {
        bail!("--video {}: is a directory", out.display());
    }
    Ok(())
}

/// Writes `frames` (all the same size) as a video at `out`: a `.gif` path is always a
/// GIF; anything else is an MP4 when ffmpeg runs, else a GIF beside it (`out` with the
/// extension `.gif`), with a note on standard error.
pub fn write_video(frames: &[RgbImage], out: &Path, fps: f64) -> Result<Video> {
    check(out, fps)?;
    let Some(first) = frames.first() else {
        bail!("no frames to write to {}", out.display());
    };
    if frames
        .iter()
        .any(|f| (f.width, f.height) != (first.width, first.height))
    {
        bail!("{}: frames differ in size", out.display());
    }
    if let Some(dir) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    let is_gif = out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("gif"));
    if is_gif {
        write_gif(frames, out, fps)?;
        return Ok(Video::Gif(out.to_path_buf()));
    }
    match ffmpeg() {
        Some(prog) => {
            write_mp4(&prog, frames, out, fps)?;
            Ok(Video::Mp4(out.to_path_buf()))
        }
        None => {
            let gif = out.with_extension("gif");
            eprintln!(
                "note: ffmpeg is not on the PATH, so the video is an animated GIF: {} (install ffmpeg for {})",
                gif.display(),
                out.display()
            );
            write_gif(frames, &gif, fps)?;
            Ok(Video::Gif(gif))
        }
    }
}

/// A temporary path beside `out` with the same extension (ffmpeg picks the container by it).
fn temp_beside(out: &Path) -> PathBuf {
    let name = out.file_name().unwrap_or_default().to_string_lossy();
    let ext = out
        .extension()
        .map(|e| format!(".{}", e.to_string_lossy()))
        .unwrap_or_default();
    out.with_file_name(format!(".{name}.{}.tmp{ext}", std::process::id()))
}

/// Moves `tmp` to `out`, or removes it when `result` is an error.
fn finish(tmp: &Path, out: &Path, result: Result<()>) -> Result<()> {
    let result = result.and_then(|()| {
        std::fs::rename(tmp, out).with_context(|| format!("cannot write {}", out.display()))
    });
    if result.is_err() {
        let _ = std::fs::remove_file(tmp);
    }
    result
}

fn write_mp4(prog: &str, frames: &[RgbImage], out: &Path, fps: f64) -> Result<()> {
    let (w, h) = (frames[0].width, frames[0].height);
    let tmp = temp_beside(out);
    let _pending = crate::cmd::support::outdir::Pending::new(&tmp);
    let result = (|| -> Result<()> {
        let mut child = Command::new(prog)
            .args([
                "-y",
                "-loglevel",
                "error",
                "-f",
                "rawvideo",
                "-pix_fmt",
                "rgb24",
            ])
            .args([
                "-s",
                &format!("{w}x{h}"),
                "-r",
                &format!("{fps}"),
                "-i",
                "-",
            ])
            .args(["-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2"])
            .args(["-c:v", "libx264", "-crf", H264_CRF, "-pix_fmt", "yuv420p"])
            .args(["-movflags", "+faststart"])
            .arg(&tmp)
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .with_context(|| format!("cannot run {prog}"))?;
        let mut stdin = child.stdin.take().context("ffmpeg's standard input")?;
        let fed = frames
            .iter()
            .try_for_each(|f| stdin.write_all(&f.to_rgb8()));
        drop(stdin);
        let done = child
            .wait_with_output()
            .with_context(|| format!("{prog} did not finish"))?;
        if !done.status.success() {
            bail!(
                "{prog} failed writing {}: {}",
                out.display(),
                String::from_utf8_lossy(&done.stderr).trim()
            );
        }
        fed.with_context(|| format!("cannot feed frames to {prog}"))?;
        Ok(())
    })();
    finish(&tmp, out, result)
}

fn write_gif(frames: &[RgbImage], out: &Path, fps: f64) -> Result<()> {
    use image::codecs::gif::{GifEncoder, Repeat};
    use image::{Delay, Frame, RgbaImage};
    let tmp = temp_beside(out);
    let _pending = crate::cmd::support::outdir::Pending::new(&tmp);
    let result = (|| -> Result<()> {
        let file = std::fs::File::create(&tmp)
            .with_context(|| format!("cannot create {}", tmp.display()))?;
        let mut enc = GifEncoder::new_with_speed(std::io::BufWriter::new(file), GIF_SPEED);
        enc.set_repeat(Repeat::Infinite)?;
        let delay = Delay::from_numer_denom_ms(1000, fps.round().max(1.0) as u32);
        for f in frames {
            let rgba: Vec<u8> = f
                .to_rgb8()
                .chunks_exact(3)
                .flat_map(|c| [c[0], c[1], c[2], 255])
                .collect();
            let buf = RgbaImage::from_raw(f.width, f.height, rgba).context("frame buffer")?;
            enc.encode_frame(Frame::from_parts(buf, 0, 0, delay))
                .with_context(|| format!("cannot encode {}", out.display()))?;
        }
        drop(enc);
        Ok(())
    })();
    finish(&tmp, out, result)
}
