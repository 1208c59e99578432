//! Model weights as safetensors, with the [`Config`] serialized in the metadata.
//!
//! Loading is strict: every tensor the model expects must be present with its exact shape
//! and finite values, and any tensor the model does not know is an error (the PyTorch
//! reference applies the same check to the same file).

use crate::config::Config;
use crate::error::{Error, Result};
use crate::model::DeepStereo;
use crate::tensorio::{f32_values, write_safetensors, NamedArray};
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use safetensors::SafeTensors;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

/// Metadata key holding the config JSON.
pub const CONFIG_KEY: &str = "deepstereo.config";
/// Metadata key identifying the file kind.
pub const FORMAT_KEY: &str = "format";
/// Value of [`FORMAT_KEY`].
pub const FORMAT_VALUE: &str = "deepstereo-weights-v1";

/// A model together with the variables that hold its weights (for training).
pub struct Trainable {
    pub model: DeepStereo,
    pub varmap: VarMap,
}

/// Builds a freshly initialised model in f32 on `device`.
pub fn init(cfg: &Config, device: &Device) -> Result<Trainable> {
    init_dtype(cfg, DType::F32, device)
}

/// Builds a freshly initialised model in `dtype` (f64 for gradient checks), seed 0.
pub fn init_dtype(cfg: &Config, dtype: DType, device: &Device) -> Result<Trainable> {
    init_seeded(cfg, dtype, device, 0)
}

/// Builds a model initialised deterministically from `seed`: PyTorch's default
/// (Kaiming-uniform) bounds `1/sqrt(fan_in)` for weights and biases, drawn from a
/// splitmix64 stream per tensor name, so a run is reproducible bit for bit.
pub fn init_seeded(cfg: &Config, dtype: DType, device: &Device, seed: u64) -> Result<Trainable> {
    let varmap = VarMap::new();
    let model = DeepStereo::new(cfg, VarBuilder::from_varmap(&varmap, dtype, device))?;
    reinit(&varmap, seed)?;
    if cfg.colour_skip || cfg.pool.is_some() {
        init_colour_mean(cfg, &varmap)?;
    }
    if let Some(hidden) = cfg.pool.as_ref().and_then(|p| p.weigh.as_ref()) {
        zero_layer(&varmap, &format!("views.weigh.{}", hidden.len()))?;
    }
    Ok(Trainable { model, varmap })
}

/// Sets a layer's weight and bias to zero: the cue's view-weight layer starts there, so
/// every view's factor starts at 1 (a random start saturates `tanh`, which leaves some
/// pixels one view and the blend no gradient).
fn zero_layer(varmap: &VarMap, stem: &str) -> Result<()> {
    for (name, var) in named_vars(varmap) {
        if name == format!("{stem}.weight") || name == format!("{stem}.bias") {
            var.set(&var.as_tensor().zeros_like()?)?;
        }
    }
    Ok(())
}

fn splitmix(z: &mut u64) -> u64 {
    *z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut x = *z;
    x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    x ^ (x >> 31)
}

/// Re-draws every weight and bias from a seeded stream (candle's CPU initialiser is
/// not seedable). `log_scale` keeps its constant.
fn reinit(varmap: &VarMap, seed: u64) -> Result<()> {
    let vars = named_vars(varmap);
    for (name, var) in &vars {
        let Some(stem) = name
            .strip_suffix(".weight")
            .or_else(|| name.strip_suffix(".bias"))
        else {
            continue;
        };
        let wname = format!("{stem}.weight");
        let fan_in: usize = match vars.iter().find(|(n, _)| *n == wname) {
            Some((_, w)) => w.as_tensor().dims().iter().skip(1).product(),
            None => continue,
        };
        let bound = 1.0 / (fan_in.max(1) as f64).sqrt();
        let mut state = seed
            ^ name.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
                (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
            });
        let n = var.as_tensor().elem_count();
        let data: Vec<f32> = (0..n)
            .map(|_| {
                ((splitmix(&mut state) >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0) * bound
            })
            .map(|v| v as f32)
            .collect();
        let t =
            Tensor::from_vec(data, var.as_tensor().dims(), var.device())?.to_dtype(var.dtype())?;
        var.set(&t)?;
    }
    Ok(())
}

/// Scale of the random part of `colour.out`'s initial weights.
const COLOUR_OUT_INIT_SCALE: f64 = 0.1;

/// Starts the colour tower's linear layer near "the mean of the sources' colours" (the
/// raw RGBA skip, weight `1/V` on each source's matching channel) plus small random
/// weights, so training starts from a sensible image instead of black. In the
/// any-number-of-views family the blend already gives the sources' colours, so the
/// linear layer (a correction added to it) starts small.
fn init_colour_mean(cfg: &Config, varmap: &VarMap) -> Result<()> {
    let vars = named_vars(varmap);
    let Some((_, w)) = vars.iter().find(|(n, _)| n == "colour.out.weight") else {
        return Ok(());
    };
    let (cout, cin) = (w.as_tensor().dim(0)?, w.as_tensor().dim(1)?);
    let mut data = tensor_f32(w.as_tensor())?;
    for v in data.iter_mut() {
        *v *= COLOUR_OUT_INIT_SCALE as f32;
    }
    let skip0 = cin.saturating_sub(cfg.in_channels());
    for k in (0..cfg.views).filter(|_| cfg.colour_skip) {
        for c in 0..cout {
            data[c * cin + skip0 + 4 * k + c] += 1.0 / cfg.views as f32;
        }
    }
    let t = Tensor::from_vec(data, w.as_tensor().dims(), w.device())?.to_dtype(w.dtype())?;
    w.set(&t)?;
    if let Some((_, b)) = vars.iter().find(|(n, _)| n == "colour.out.bias") {
        b.set(&b.as_tensor().zeros_like()?)?;
    }
    Ok(())
}

/// The variables of a model, sorted by name.
pub fn named_vars(varmap: &VarMap) -> Vec<(String, candle_core::Var)> {
    let data = varmap.data().lock().map(|d| d.clone()).unwrap_or_default();
    let sorted: BTreeMap<String, candle_core::Var> = data.into_iter().collect();
    sorted.into_iter().collect()
}

/// Flattens a tensor to f32 values.
pub fn tensor_f32(t: &Tensor) -> Result<Vec<f32>> {
    Ok(t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?)
}

/// The weights (and extra tensors, such as optimizer state) as named arrays.
pub fn weight_arrays(varmap: &VarMap) -> Result<Vec<NamedArray>> {
    named_vars(varmap)
        .iter()
        .map(|(name, var)| {
            let t = var.as_tensor();
            Ok(NamedArray::f32(name, t.dims(), &tensor_f32(t)?))
        })
        .collect()
}

/// Metadata for a weights file of `cfg`, plus `extra` entries.
pub fn metadata(cfg: &Config, extra: &[(&str, String)]) -> Result<HashMap<String, String>> {
    let mut m = HashMap::new();
    let json = serde_json::to_string(cfg)
        .map_err(|e| Error::Invalid(format!("cannot serialize config: {e}")))?;
    m.insert(CONFIG_KEY.to_string(), json);
    m.insert(FORMAT_KEY.to_string(), FORMAT_VALUE.to_string());
    for (k, v) in extra {
        m.insert(k.to_string(), v.clone());
    }
    Ok(m)
}

/// Saves the weights of `varmap` (a model of `cfg`) atomically, refusing non-finite values.
pub fn save(path: &Path, cfg: &Config, varmap: &VarMap) -> Result<()> {
    save_with_prior(path, cfg, varmap, None, &[])
}

/// Saves the weights of `varmap` (a model of `cfg`), a scene `prior` when given, and the
/// metadata entries `extra`, atomically, refusing non-finite values.
pub fn save_with_prior(
    path: &Path,
    cfg: &Config,
    varmap: &VarMap,
    prior: Option<&crate::prior::PriorGrid>,
    extra: &[(&str, String)],
) -> Result<()> {
    let mut arrays = weight_arrays(varmap)?;
    let mut extra = extra.to_vec();
    if let Some(grid) = prior {
        let (array, entry) = crate::prior::io::to_file(grid);
        arrays.push(array);
        extra.push(entry);
    }
    check_finite(path, &arrays)?;
    write_safetensors(path, &arrays, Some(metadata(cfg, &extra)?))
}

/// Errors if any f32 array holds NaN or infinity.
pub fn check_finite(path: &Path, arrays: &[NamedArray]) -> Result<()> {
    for a in arrays {
        if a.bytes
            .chunks_exact(4)
            .any(|b| !f32::from_le_bytes([b[0], b[1], b[2], b[3]]).is_finite())
        {
            return Err(Error::model(
                path,
                format!("tensor '{}' holds non-finite values", a.name),
            ));
        }
    }
    Ok(())
}

/// Checks a safetensors file's header against its data, naming the tensor whose entry is
/// wrong: each entry's bytes must match its dtype and shape, and the entries must tile the
/// data in order (the safetensors crate reports a broken entry as an offset error of the
/// tensor after it). The crate's own checks run after this one.
pub fn check_layout(path: &Path, bytes: &[u8]) -> Result<()> {
    let bad = |msg: String| Error::model(path, format!("not a valid safetensors file: {msg}"));
    let head = bytes
        .get(..8)
        .and_then(|b| <[u8; 8]>::try_from(b).ok())
        .ok_or_else(|| bad("shorter than its 8-byte header length".into()))?;
    let n = usize::try_from(u64::from_le_bytes(head)).unwrap_or(usize::MAX);
    let json = bytes.get(8..8usize.saturating_add(n)).ok_or_else(|| {
        bad(format!(
            "the header claims {n} bytes, beyond the file's end"
        ))
    })?;
    let header: serde_json::Map<String, serde_json::Value> = serde_json::from_slice(json)
        .map_err(|e| bad(format!("the header is not a JSON object: {e}")))?;
    let data_len = bytes.len() - 8 - n;
    let mut entries = Vec::new();
    for (name, v) in header.iter().filter(|(k, _)| *k != "__metadata__") {
        let entry = |msg: &str| bad(format!("tensor '{name}': {msg}"));
        let size = match v.get("dtype").and_then(|d| d.as_str()) {
            Some("F64" | "I64" | "U64") => 8u64,
            Some("F32" | "I32" | "U32") => 4,
            Some("F16" | "BF16" | "I16" | "U16") => 2,
            Some("U8" | "I8" | "BOOL" | "F8_E4M3" | "F8_E5M2") => 1,
            _ => return Err(entry("no known 'dtype'")),
        };
        let nums = |key: &str| -> Option<Vec<u64>> {
            v.get(key)?.as_array()?.iter().map(|x| x.as_u64()).collect()
        };
        let shape = nums("shape").ok_or_else(|| entry("no valid 'shape'"))?;
        let offs = nums("data_offsets")
            .filter(|o| o.len() == 2 && o[0] <= o[1])
            .ok_or_else(|| entry("no valid 'data_offsets' [begin, end]"))?;
        let want = shape.iter().try_fold(size, |a, &d| a.checked_mul(d));
        if want != Some(offs[1] - offs[0]) {
            return Err(entry(&format!(
                "its shape {shape:?} needs {} bytes but its data_offsets {offs:?} hold {}",
                want.map_or("too many".to_string(), |w| w.to_string()),
                offs[1] - offs[0]
            )));
        }
        entries.push((offs[0], offs[1], name.as_str()));
    }
    entries.sort();
    let mut end = (0u64, None::<&str>);
    for &(b, e, name) in &entries {
        if b != end.0 {
            return Err(bad(match end.1 {
                Some(prev) => format!(
                    "tensor '{prev}' ends at data byte {} but the next one, '{name}', starts at {b}: one of their entries is wrong",
                    end.0
                ),
                None => format!("the first tensor, '{name}', starts at data byte {b}, not 0"),
            }));
        }
        end = (e, Some(name));
    }
    if end.0 != data_len as u64 {
        return Err(bad(format!(
            "the tensors end at data byte {} but the file holds {data_len} data bytes{}",
            end.0,
            end.1.map(|n| format!(" (last: '{n}')")).unwrap_or_default()
        )));
    }
    Ok(())
}

/// Reads the config stored in a weights file's metadata.
pub fn read_config(path: &Path, bytes: &[u8]) -> Result<Config> {
    check_layout(path, bytes)?;
    let (_, meta) = SafeTensors::read_metadata(bytes)
        .map_err(|e| Error::model(path, format!("not a safetensors file: {e}")))?;
    let json = meta
        .metadata()
        .as_ref()
        .and_then(|m| m.get(CONFIG_KEY))
        .ok_or_else(|| {
            Error::model(
                path,
                format!("no '{CONFIG_KEY}' in the metadata: not a deepstereo weights file"),
            )
        })?;
    let cfg: Config = serde_json::from_str(json)
        .map_err(|e| Error::model(path, format!("invalid config in the metadata: {e}")))?;
    cfg.validate()
        .map_err(|m| Error::model(path, format!("invalid config: {m}")))?;
    Ok(cfg)
}

/// Loads a model from safetensors bytes (`path` names them in errors), strictly.
pub fn load_bytes(path: &Path, bytes: &[u8], device: &Device) -> Result<Trainable> {
    let cfg = read_config(path, bytes)?;
    let st = SafeTensors::deserialize(bytes)
        .map_err(|e| Error::model(path, format!("not a safetensors file: {e}")))?;
    check_size(path, &cfg, &st)?;
    let mut t = init(&cfg, device)?;
    assign(path, &st, &t.varmap, "")?;
    let prior = crate::prior::io::read(path, bytes, &st)?;
    t.model = t.model.with_prior(prior);
    let expected: Vec<String> = named_vars(&t.varmap).into_iter().map(|(n, _)| n).collect();
    if let Some(extra) = st
        .names()
        .into_iter()
        .filter(|n| *n != crate::prior::io::TENSOR)
        .find(|n| !expected.iter().any(|e| e == *n))
    {
        return Err(Error::model(
            path,
            format!(
                "unexpected tensor '{extra}' (not part of a '{}' model)",
                cfg.name
            ),
        ));
    }
    Ok(t)
}

/// Refuses, before the model is allocated, a config that needs more parameters than the
/// file holds values (so a corrupt config cannot request a huge allocation), naming the
/// first missing tensor when there is one.
fn check_size(path: &Path, cfg: &Config, st: &SafeTensors<'_>) -> Result<()> {
    let held = st
        .tensors()
        .iter()
        .map(|(_, v)| {
            v.shape()
                .iter()
                .try_fold(1usize, |a, &d| a.checked_mul(d))
                .unwrap_or(usize::MAX)
        })
        .fold(0usize, usize::saturating_add);
    let needed = cfg.parameters();
    if needed <= held {
        return Ok(());
    }
    let names = cfg
        .layers()
        .into_iter()
        .flat_map(|l| [format!("{}.weight", l.name), format!("{}.bias", l.name)]);
    let missing = names
        .chain(["select.log_scale".to_string()])
        .find(|n| st.tensor(n).is_err());
    Err(Error::model(
        path,
        match missing {
            Some(n) => format!("missing tensor '{n}'"),
            None => format!(
                "the '{}' config needs {needed} parameters but the file holds {held} values",
                cfg.name
            ),
        },
    ))
}

/// Loads a model from a weights file.
pub fn load(path: &Path, device: &Device) -> Result<Trainable> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    load_bytes(path, &bytes, device)
}

/// Sets every variable of `varmap` from tensor `prefix + name` of `st`, checking shapes
/// and finiteness.
pub fn assign(path: &Path, st: &SafeTensors<'_>, varmap: &VarMap, prefix: &str) -> Result<()> {
    for (name, var) in named_vars(varmap) {
        let key = format!("{prefix}{name}");
        let view = st
            .tensor(&key)
            .map_err(|_| Error::model(path, format!("missing tensor '{key}'")))?;
        let want = var.as_tensor().dims().to_vec();
        if view.shape() != want.as_slice() {
            return Err(Error::model(
                path,
                format!(
                    "tensor '{key}' has shape {:?}, the model expects {want:?}",
                    view.shape()
                ),
            ));
        }
        if view.dtype() != safetensors::Dtype::F32 {
            return Err(Error::model(
                path,
                format!("tensor '{key}' is {:?}, expected F32", view.dtype()),
            ));
        }
        let data = f32_values(&view);
        if data.iter().any(|v| !v.is_finite()) {
            return Err(Error::model(
                path,
                format!("tensor '{key}' holds non-finite values"),
            ));
        }
        let t = Tensor::from_vec(data, want.as_slice(), var.device())?.to_dtype(var.dtype())?;
        var.set(&t)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::check_layout;
    use std::path::Path;

    /// A safetensors file of `header` (JSON) and `data` bytes.
    fn file(header: &str, data: usize) -> Vec<u8> {
        let mut b = (header.len() as u64).to_le_bytes().to_vec();
        b.extend(header.as_bytes());
        b.extend(vec![0u8; data]);
        b
    }

    #[test]
    fn a_broken_header_entry_is_named_not_the_tensor_after_it() {
        let p = Path::new("m.safetensors");
        let good = r#"{"out.bias":{"dtype":"F32","shape":[3],"data_offsets":[0,12]},"out.weight":{"dtype":"F32","shape":[2,3],"data_offsets":[12,36]}}"#;
        check_layout(p, &file(good, 36)).expect("a valid file");
        // The bias entry shortened to two values: the gap is named with both tensors.
        let short = good.replace(
            r#""shape":[3],"data_offsets":[0,12]"#,
            r#""shape":[2],"data_offsets":[0,8]"#,
        );
        let e = check_layout(p, &file(&short, 36))
            .expect_err("gap")
            .to_string();
        assert!(
            e.contains("'out.bias' ends at data byte 8") && e.contains("'out.weight'"),
            "{e}"
        );
        // Its shape changed but not its offsets: the bias is named alone.
        let shape = good.replace(r#""shape":[3]"#, r#""shape":[4]"#);
        let e = check_layout(p, &file(&shape, 36))
            .expect_err("shape")
            .to_string();
        assert!(
            e.contains("tensor 'out.bias'") && e.contains("needs 16 bytes"),
            "{e}"
        );
        assert!(!e.contains("out.weight"), "{e}");
        // Data missing at the end, and a header longer than the file.
        let e = check_layout(p, &file(good, 30))
            .expect_err("short")
            .to_string();
        assert!(
            e.contains("30 data bytes") && e.contains("'out.weight'"),
            "{e}"
        );
        let mut long = file(good, 36);
        long[..8].copy_from_slice(&1_000_000u64.to_le_bytes());
        let e = check_layout(p, &long).expect_err("long").to_string();
        assert!(e.contains("beyond the file's end"), "{e}");
    }
}
