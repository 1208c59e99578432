//! [`Config::layers`]: every layer with its shapes, parameters and cost (the README's
//! table), and the totals from it.

use super::*;

/// One row of the layer table.
#[derive(Clone, Debug, PartialEq)]
pub struct LayerInfo {
    pub name: String,
    pub kernel: usize,
    pub in_channels: usize,
    pub out_channels: usize,
    /// Output side for a training tile.
    pub out_size: usize,
    pub params: usize,
    pub macs_per_pixel: f64,
}

impl LayerInfo {
    fn new(name: String, conv: Conv, cin: usize, out_size: usize, macs_per_pixel: f64) -> Self {
        Self {
            name,
            kernel: conv.kernel,
            in_channels: cin,
            out_channels: conv.channels,
            out_size,
            params: conv.kernel * conv.kernel * cin * conv.channels + conv.channels,
            macs_per_pixel,
        }
    }
}

/// The rows `{prefix}.{i}` of the square convolutions `convs` (valid) on `ch` channels of
/// side `size`, their multiply-adds times `d / area` (planes over output pixels); returns
/// the channels after them.
fn conv_rows(
    prefix: &str,
    convs: &[Conv],
    (mut ch, mut size): (usize, usize),
    (d, area): (f64, f64),
    out: &mut Vec<LayerInfo>,
) -> usize {
    for (i, conv) in convs.iter().enumerate() {
        size -= conv.kernel - 1;
        let macs = (size * size * conv.kernel * conv.kernel * ch * conv.channels) as f64;
        out.push(LayerInfo::new(
            format!("{prefix}.{i}"),
            *conv,
            ch,
            size,
            macs * d / area,
        ));
        ch = conv.channels;
    }
    ch
}

impl Config {
    /// Parameter count.
    pub fn parameters(&self) -> usize {
        self.layers().iter().map(|l| l.params).sum::<usize>() + 1
    }

    /// Multiply-adds per output pixel, for a training tile, with `self.planes` planes.
    pub fn macs_per_pixel(&self) -> f64 {
        self.layers().iter().map(|l| l.macs_per_pixel).sum()
    }

    /// Every layer with its shapes, parameters and cost, in order (for the README table).
    pub fn layers(&self) -> Vec<LayerInfo> {
        let mut out = Vec::new();
        if let Some(pool) = &self.pool {
            if let Some(f) = &pool.features {
                self.feature_layers(f, &mut out);
            }
            self.encoder_layers(pool, &mut out);
        }
        for (name, tower) in [("select", &self.select), ("colour", &self.colour)] {
            let ch = self.tower_layers(name, tower, &mut out);
            if name == "select" {
                self.depth_layers(ch, &mut out);
            } else {
                self.colour_out_layers(ch, &mut out);
            }
        }
        out
    }

    /// The features family's per-source CNN: run once on each source image at every level,
    /// so per output pixel it costs the default `views` times `sum_l 4^-l` of its
    /// multiply-adds per source pixel, whatever the planes.
    fn feature_layers(&self, f: &SourceFeatures, out: &mut Vec<LayerInfo>) {
        let share: f64 = (0..self.levels).map(|l| 0.25f64.powi(l as i32)).sum();
        let mut ch = 3;
        for (i, conv) in f.convs.iter().enumerate() {
            let macs = (conv.kernel * conv.kernel * ch * conv.channels) as f64;
            let name = format!("features.{i}");
            out.push(LayerInfo::new(
                name,
                *conv,
                ch,
                self.tile,
                macs * share * self.views as f64,
            ));
            ch = conv.channels;
        }
    }

    /// The pool's per-view layers, on every level's whole input, each of the default
    /// `views` views: the cue's view weights (`views.weigh.*`: hidden layers, then one
    /// channel), then the encoder.
    fn encoder_layers(&self, pool: &ViewPool, out: &mut Vec<LayerInfo>) {
        let weigh = pool.weigh.iter().flatten().copied();
        let one = pool.weigh.as_ref().map(|_| Conv {
            kernel: 1,
            channels: 1,
        });
        self.view_rows("views.weigh", weigh.chain(one), pool.cue_channels(), out);
        let encoder = pool.encoder.iter().copied();
        self.view_rows("views.encode", encoder, pool.encoder_in(), out);
    }

    /// The rows `{prefix}.{i}` of 1x1 layers `convs` on `ch` channels run per view and
    /// plane on every level's whole input.
    fn view_rows(
        &self,
        prefix: &str,
        convs: impl Iterator<Item = Conv>,
        mut ch: usize,
        out: &mut Vec<LayerInfo>,
    ) {
        let t = self.tile;
        let (d, area) = (self.planes as f64, (t * t) as f64);
        let pixels: usize = (0..self.levels).map(|l| self.input_size(l, t).pow(2)).sum();
        for (i, conv) in convs.enumerate() {
            let macs = (pixels * ch * conv.channels * self.views) as f64;
            let name = format!("{prefix}.{i}");
            out.push(LayerInfo::new(name, conv, ch, t, macs * d / area));
            ch = conv.channels;
        }
    }

    /// Tower `name`'s per-level and merge convolutions; returns its output channels.
    fn tower_layers(&self, name: &str, tower: &TowerConfig, out: &mut Vec<LayerInfo>) -> usize {
        let t = self.tile;
        let (d, area) = (self.planes as f64, (t * t) as f64);
        let cin = self.tower_in_channels();
        let rf = tower.merge_reduction();
        for l in 0..tower.levels {
            let size = (t >> l) + 2 * tower.pad(l);
            let prefix = format!("{name}.levels.{l}");
            conv_rows(&prefix, &tower.level_convs, (cin, size), (d, area), out);
        }
        let ch = tower.level_channels(cin) * tower.levels;
        let prefix = format!("{name}.merge");
        conv_rows(&prefix, &tower.merge_convs, (ch, t + rf), (d, area), out)
    }

    /// The selection tower's depth convolutions, after its `ch` channels.
    fn depth_layers(&self, mut ch: usize, out: &mut Vec<LayerInfo>) {
        let d = self.planes as f64;
        for (i, conv) in self.depth_convs.iter().enumerate() {
            let macs = (conv.kernel * ch * conv.channels) as f64 * d;
            let mut info = LayerInfo::new(format!("select.depth.{i}"), *conv, ch, self.tile, macs);
            info.params = conv.kernel * ch * conv.channels + conv.channels;
            out.push(info);
            ch = conv.channels;
        }
    }

    /// The colour tower's RGB output after its `ch` channels, and the pool's blend head.
    fn colour_out_layers(&self, ch: usize, out: &mut Vec<LayerInfo>) {
        let (t, d) = (self.tile, self.planes as f64);
        let cin = self.tower_in_channels();
        let cin_out = ch + if self.colour_skip { cin } else { 0 };
        let conv = Conv {
            kernel: 1,
            channels: 3,
        };
        out.push(LayerInfo::new(
            "colour.out".into(),
            conv,
            cin_out,
            t,
            (cin_out * 3) as f64 * d,
        ));
        if let Some(pool) = &self.pool {
            let mut hin = pool.features() + ch;
            let hidden = pool.blend.iter().chain([&Conv {
                kernel: 1,
                channels: 1,
            }]);
            for (i, conv) in hidden.enumerate() {
                let macs = (hin * conv.channels * self.views) as f64 * d;
                out.push(LayerInfo::new(
                    format!("colour.blend.{i}"),
                    *conv,
                    hin,
                    t,
                    macs,
                ));
                hin = conv.channels;
            }
        }
    }
}
