//! Options and values shared by several commands: how to read a scene ([`SceneArgs`]),
//! how to run a model ([`ModelArgs`]), how training samples are drawn ([`SamplingArgs`]),
//! and the parsers of the values they take (sizes, ranges, model configs).

pub mod choice;
pub mod holdout;
pub mod input;
pub mod model;
pub mod sampling;
pub mod scene;

pub use choice::choice;
pub use holdout::HoldoutArgs;
pub use input::SceneModelArgs;
pub use model::ModelArgs;
pub use sampling::SamplingArgs;
pub use scene::SceneArgs;

/// The help heading of the options few runs need (pruning's knobs, how a scene's files are
/// read, tiling): `--help` lists them after the others, documented in docs/commands.md.
pub const EXPERT: &str = "Expert options (docs/commands.md)";

use anyhow::{bail, Context};
use deepstereo_core::config::Config;
use std::path::Path;

/// Parses `K` or `MIN-MAX` for option `name`.
pub fn parse_range_of(name: &str, s: &str) -> anyhow::Result<(usize, usize)> {
    let parse = |t: &str| -> anyhow::Result<usize> {
        t.trim()
            .parse()
            .with_context(|| format!("{name} '{s}': '{t}' is not a whole number"))
    };
    let (lo, hi) = match s.split_once('-') {
        Some((a, b)) => (parse(a)?, parse(b)?),
        None => (parse(s)?, parse(s)?),
    };
    if lo == 0 || lo > hi {
        bail!("{name} '{s}': expected K or MIN-MAX with 1 <= MIN <= MAX");
    }
    Ok((lo, hi))
}

/// Parses an image size, `WIDTHxHEIGHT` (positive whole numbers; `X` also separates
/// them). The error is a message, as clap's value parsers return.
pub fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let bad =
        || format!("expected WIDTHxHEIGHT with positive whole numbers, such as 160x120, got '{s}'");
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let w: u32 = w.trim().parse().map_err(|_| bad())?;
    let h: u32 = h.trim().parse().map_err(|_| bad())?;
    if w == 0 || h == 0 {
        return Err(bad());
    }
    Ok((w, h))
}

/// [`parse_size`] of option `name`'s value, the error naming the option.
pub fn size_of(name: &str, s: &str) -> anyhow::Result<(u32, u32)> {
    parse_size(s).map_err(|m| anyhow::anyhow!("{name}: {m}"))
}

/// A preset name or a JSON config file (`--config`).
pub fn load_config(s: &str) -> anyhow::Result<Config> {
    if let Some(c) = Config::preset(s) {
        return Ok(c);
    }
    let p = Path::new(s);
    let text = std::fs::read_to_string(p).with_context(|| {
        format!(
            "--config '{s}' is neither a preset ({}) nor a readable file",
            Config::PRESETS.join(", ")
        )
    })?;
    let c: Config = serde_json::from_str(&text)
        .with_context(|| format!("{}: invalid config JSON", p.display()))?;
    c.validate()
        .map_err(|m| anyhow::anyhow!("{}: {m}", p.display()))?;
    Ok(c)
}

#[cfg(test)]
mod tests {
    use super::{parse_range_of, parse_size, size_of};

    #[test]
    fn sizes_parse() {
        assert_eq!(parse_size("160x120"), Ok((160, 120)));
        assert_eq!(parse_size("64X48"), Ok((64, 48)));
        for bad in ["160", "0x120", "160x0", "axb", "-1x5", "160x120x3", ""] {
            assert!(parse_size(bad).is_err(), "{bad}");
        }
        let e = size_of("--size", "12").unwrap_err().to_string();
        assert!(e.starts_with("--size: expected WIDTHxHEIGHT"), "{e}");
    }

    #[test]
    fn ranges_parse() {
        assert_eq!(parse_range_of("--views", "3").unwrap(), (3, 3));
        assert_eq!(parse_range_of("--views", "2-8").unwrap(), (2, 8));
        for bad in ["0", "5-2", "a", "1-", ""] {
            assert!(parse_range_of("--views", bad).is_err(), "{bad}");
        }
    }
}
