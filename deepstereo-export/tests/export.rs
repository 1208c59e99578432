//! The exported graph: its structure, and onnxruntime against candle on random inputs.

use candle_core::{Device, Tensor};
use deepstereo_core::config::{Config, Conv, TowerConfig};
use deepstereo_core::weights::{self, Trainable};
use deepstereo_export::onnx_proto::ModelProto;
use deepstereo_export::{
    export, export_trainable, model_weights, read_config, Error, OrtBackend, DEFAULT_OPSET,
};
use prost::Message;

/// A config that exercises what `tiny` does not: three levels, towers reading different
/// numbers of levels, 5x5 kernels, no colour skip.
fn variant() -> Config {
    let c = |kernel, channels| Conv { kernel, channels };
    Config {
        name: "variant".into(),
        views: 2,
        planes: 6,
        levels: 3,
        tile: 8,
        select: TowerConfig {
            levels: 3,
            level_convs: vec![c(3, 6), c(3, 5)],
            merge_convs: vec![c(5, 7), c(3, 4)],
        },
        depth_convs: vec![c(3, 4), c(5, 1)],
        colour: TowerConfig {
            levels: 2,
            level_convs: vec![c(3, 5)],
            merge_convs: vec![c(3, 6)],
        },
        colour_skip: false,
        render_planes: None,
        pool: None,
    }
}

fn random_inputs(
    cfg: &Config,
    b: usize,
    d: usize,
    th: usize,
    tw: usize,
) -> anyhow::Result<Vec<Tensor>> {
    (0..cfg.levels)
        .map(|l| {
            let shape = (
                b,
                d,
                cfg.in_channels(),
                cfg.input_size(l, th),
                cfg.input_size(l, tw),
            );
            Ok(Tensor::rand(0f32, 1f32, shape, &Device::Cpu)?)
        })
        .collect()
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn exported_model_round_trips_through_prost() -> anyhow::Result<()> {
    for cfg in [Config::tiny(), variant()] {
        let t = weights::init(&cfg, &Device::Cpu)?;
        let bytes = export_trainable(&t, DEFAULT_OPSET)?;
        let model = ModelProto::decode(bytes.as_slice())?;
        assert_eq!(model.encode_to_vec(), bytes);
        assert_eq!(read_config(&bytes)?, cfg);
        assert_eq!(model.opset_import[0].version, Some(17));
        assert_eq!(model.ir_version, Some(8));
        let graph = model.graph.as_ref().expect("graph");
        let inputs: Vec<&str> = graph
            .input
            .iter()
            .filter_map(|i| i.name.as_deref())
            .collect();
        let want: Vec<String> = (0..cfg.levels).map(|l| format!("level{l}")).collect();
        assert_eq!(inputs, want);
        let outputs: Vec<&str> = graph
            .output
            .iter()
            .filter_map(|i| i.name.as_deref())
            .collect();
        assert_eq!(outputs, ["image", "selection"]);
        let mut init: Vec<&str> = graph
            .initializer
            .iter()
            .filter_map(|i| i.name.as_deref())
            .collect();
        init.sort();
        let names: Vec<String> = model_weights(&t)?.into_iter().map(|(n, _, _)| n).collect();
        assert_eq!(init, names);
        assert!(names.iter().any(|n| n == "select.levels.0.0.weight"));
        assert!(names.iter().any(|n| n == "select.log_scale"));
    }
    Ok(())
}

#[test]
fn mismatched_weights_are_rejected() -> anyhow::Result<()> {
    let cfg = Config::tiny();
    let t = weights::init(&cfg, &Device::Cpu)?;
    let w = model_weights(&t)?;
    let missing: Vec<_> = w
        .iter()
        .filter(|(n, _, _)| n != "colour.out.bias")
        .cloned()
        .collect();
    let e = export(&cfg, &missing, 17).unwrap_err();
    assert!(
        matches!(e, Error::Weights { .. })
            && e.to_string().contains("missing tensor 'colour.out.bias'"),
        "{e}"
    );
    let mut extra = w.clone();
    extra.push(("select.bogus".into(), vec![1], vec![0.0]));
    let e = export(&cfg, &extra, 17).unwrap_err();
    assert!(
        e.to_string().contains("unexpected tensor 'select.bogus'"),
        "{e}"
    );
    let mut wrong = w.clone();
    if let Some(x) = wrong.iter_mut().find(|(n, _, _)| n == "colour.out.weight") {
        x.1 = vec![x.2.len()];
    }
    let e = export(&cfg, &wrong, 17).unwrap_err();
    assert!(e.to_string().contains("has shape"), "{e}");
    assert!(matches!(export(&cfg, &w, 16), Err(Error::Opset { .. })));
    Ok(())
}

fn ort_backend(t: &Trainable, opset: i64) -> anyhow::Result<Option<OrtBackend>> {
    match OrtBackend::from_bytes(&export_trainable(t, opset)?) {
        Ok(b) => Ok(Some(b)),
        Err(Error::OrtLibrary(msg)) => {
            println!("skipping the onnxruntime comparison: {msg}");
            Ok(None)
        }
        Err(e) => Err(e.into()),
    }
}

#[test]
fn ort_matches_candle_on_random_inputs() -> anyhow::Result<()> {
    for (cfg, opset) in [(Config::tiny(), 17), (variant(), 17), (Config::tiny(), 21)] {
        let t = weights::init(&cfg, &Device::Cpu)?;
        let Some(backend) = ort_backend(&t, opset)? else {
            return Ok(());
        };
        for &(b, d, th, tw) in &[(1, 1, 8, 8), (2, 5, 8, 16), (1, 32, 24, 12)] {
            let inputs = random_inputs(&cfg, b, d, th, tw)?;
            let out = t.model.forward(&inputs)?;
            let shapes: Vec<Vec<usize>> = inputs.iter().map(|x| x.dims().to_vec()).collect();
            let data: Vec<Vec<f32>> = inputs
                .iter()
                .map(|x| x.flatten_all()?.to_vec1::<f32>())
                .collect::<candle_core::Result<_>>()?;
            let levels: Vec<(&[usize], &[f32])> = shapes
                .iter()
                .zip(&data)
                .map(|(s, d)| (s.as_slice(), d.as_slice()))
                .collect();
            let got = backend.forward(&levels)?;
            assert_eq!(got.image_shape, out.image.dims());
            assert_eq!(got.selection_shape, out.selection.dims());
            let di = max_abs_diff(&got.image, &out.image.flatten_all()?.to_vec1::<f32>()?);
            let ds = max_abs_diff(
                &got.selection,
                &out.selection.flatten_all()?.to_vec1::<f32>()?,
            );
            println!(
                "{} opset {opset} B={b} D={d} {th}x{tw}: image {di:.2e}, selection {ds:.2e}",
                cfg.name
            );
            assert!(
                di < 1e-4 && ds < 1e-4,
                "{}: image {di}, selection {ds}",
                cfg.name
            );
        }
    }
    Ok(())
}

#[test]
fn ort_backend_renders_through_the_backend_trait() -> anyhow::Result<()> {
    use deepstereo_core::inputs::TileInputs;
    use deepstereo_core::render::{Backend, CandleBackend};
    let cfg = Config::tiny();
    let t = weights::init(&cfg, &Device::Cpu)?;
    let Some(ort) = ort_backend(&t, 17)? else {
        return Ok(());
    };
    let (d, th, tw) = (3, 8, 8);
    let inputs = random_inputs(&cfg, 1, d, th, tw)?;
    let tile = TileInputs {
        levels: inputs
            .iter()
            .map(|x| x.flatten_all()?.to_vec1::<f32>())
            .collect::<candle_core::Result<_>>()?,
        sizes: (0..cfg.levels)
            .map(|l| (cfg.input_size(l, th), cfg.input_size(l, tw)))
            .collect(),
        views: cfg.views,
        channels: cfg.view_channels(),
    };
    let candle = CandleBackend {
        model: t.model.clone(),
        device: Device::Cpu,
    };
    let (ci, cs) = candle.run(&tile, d)?;
    let (oi, os) = ort.run(&tile, d)?;
    assert_eq!(ort.name(), "ort");
    assert!(max_abs_diff(&ci, &oi) < 1e-4 && max_abs_diff(&cs, &os) < 1e-4);
    Ok(())
}
