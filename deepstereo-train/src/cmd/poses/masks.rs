//! `deepstereo poses --masks DIR`: feature masks for COLMAP. A mask is a PNG of its
//! photograph's size; COLMAP extracts no features where it is black (value 0), so moving
//! things (people, cars, the turning object of a turntable capture's static room) can be
//! left out of the geometry. COLMAP's convention names the mask of `a.jpg` `a.jpg.png`;
//! `a.png` is accepted too. The masks are checked before COLMAP runs and handed to it in
//! that convention (`ImageReader.mask_path`); the scene written keeps no copy of them.

use anyhow::{bail, Context};
use deepstereo_core::scene::image_size;
use std::path::{Path, PathBuf};

/// The mask of every image of `images` in `dir`, checked: present, a PNG, readable, of
/// its photograph's size.
pub fn find_masks(dir: &Path, images: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    if !dir.is_dir() {
        bail!(
            "{}: not a directory (--masks takes a folder of PNG masks)",
            dir.display()
        );
    }
    let mut out = Vec::with_capacity(images.len());
    for img in images {
        let name = img.file_name().context("image without a file name")?;
        let stem = img.file_stem().context("image without a file name")?;
        let full = dir.join(format!("{}.png", name.to_string_lossy()));
        let short = dir.join(format!("{}.png", stem.to_string_lossy()));
        let mask = if full.is_file() {
            full
        } else if short.is_file() && short != *img {
            short
        } else {
            bail!(
                "{}: no mask for it in {} (looked for {} and {})",
                img.display(),
                dir.display(),
                full.display(),
                short.display()
            );
        };
        let (mw, mh) = image_size(&mask).with_context(|| format!("mask {}", mask.display()))?;
        let (w, h) = image_size(img)?;
        if (mw, mh) != (w, h) {
            bail!(
                "{}: the mask is {mw}x{mh} but its photograph {} is {w}x{h}",
                mask.display(),
                img.display()
            );
        }
        out.push(mask);
    }
    Ok(out)
}

/// Copies `masks` into `to` under COLMAP's names (`<image file name>.png`).
pub fn copy_masks(masks: &[PathBuf], images: &[PathBuf], to: &Path) -> anyhow::Result<()> {
    std::fs::create_dir(to).with_context(|| to.display().to_string())?;
    for (m, img) in masks.iter().zip(images) {
        let name = img.file_name().context("image without a file name")?;
        let dst = to.join(format!("{}.png", name.to_string_lossy()));
        std::fs::copy(m, &dst).with_context(|| format!("cannot copy {}", m.display()))?;
    }
    Ok(())
}
