//! Writes a freshly initialised model of a preset as a weights file (for the parity checks
//! until a trained model exists): `init_weights [PRESET] OUT.safetensors`.

use candle_core::Device;
use deepstereo_core::config::Config;
use deepstereo_core::weights;
use std::path::PathBuf;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (preset, out) = match args.as_slice() {
        [out] => ("tiny", out),
        [preset, out] => (preset.as_str(), out),
        _ => anyhow::bail!("usage: init_weights [PRESET] OUT.safetensors"),
    };
    let cfg = Config::preset(preset).ok_or_else(|| anyhow::anyhow!("unknown preset '{preset}'"))?;
    let t = weights::init(&cfg, &Device::Cpu)?;
    weights::save(&PathBuf::from(out), &cfg, &t.varmap)?;
    eprintln!("wrote {out} ({} parameters)", cfg.parameters());
    Ok(())
}
