//! The any-number-of-views family's view pooling and colour blend in the graph, step by
//! step `deepstereo_core::pool` (its module doc has the maths). The number of views `V`
//! is dynamic: read from level 0's shape.

use super::{attr_int, input_name, Graph};
use crate::error::Result;
use deepstereo_core::config::{Config, Conv, ViewPool, CUE_CHANNELS, WEIGH_SCALE};
use deepstereo_core::pool::{BLEND_EPS, BLEND_LOGIT_BOUND, POOL_EPS};

impl Graph<'_> {
    /// `Shape(x)[start..end]`.
    fn shape_of(&mut self, x: &str, start: i64, end: i64, hint: &str) -> String {
        let attrs = vec![attr_int("start", start), attr_int("end", end)];
        self.op("Shape", &[x], attrs, hint)
    }

    /// `x[..., lo..hi, ...]` on one axis.
    fn slice_axis(&mut self, x: &str, axis: i64, lo: i64, hi: i64, hint: &str) -> String {
        let s = self.const_i64(&[lo], "starts");
        let e = self.const_i64(&[hi], "ends");
        let ax = self.const_i64(&[axis], "axes");
        self.op("Slice", &[x, &s, &e, &ax], vec![], hint)
    }

    fn sum_axis(&mut self, x: &str, axis: i64, keep: bool, hint: &str) -> String {
        let ax = self.const_i64(&[axis], "axes");
        let attrs = vec![attr_int("keepdims", keep as i64)];
        self.op("ReduceSum", &[x, &ax], attrs, hint)
    }

    fn add_scalar(&mut self, x: &str, v: f64, hint: &str) -> String {
        let c = self.const_f32(&[], &[v as f32], "scalar");
        self.op("Add", &[x, &c], vec![], hint)
    }

    fn concat(&mut self, parts: &[&str], axis: i64, hint: &str) -> String {
        self.op("Concat", parts, vec![attr_int("axis", axis)], hint)
    }

    /// `weighted_mean` of `pool.rs`: `sum over axis of (t * a) / den`.
    fn weighted_mean(&mut self, t: &str, a: &str, den: &str, axis: i64, hint: &str) -> String {
        let ta = self.op("Mul", &[t, a], vec![], hint);
        let s = self.sum_axis(&ta, axis, true, hint);
        self.op("Div", &[&s, den], vec![], hint)
    }

    /// Level `l` as the view pooling and the blend read it: the graph's input, or its
    /// weighed copy ([`Self::weighed_levels`]).
    fn view_level(&self, l: usize) -> String {
        self.view_levels
            .get(l)
            .cloned()
            .unwrap_or_else(|| input_name(l))
    }

    /// `ViewWeigh::forward` on every level: `[B, D, V, 4, H, W]`, each view's RGB and its
    /// alpha times `1 + tanh(WEIGH_SCALE g(cue))`.
    pub(super) fn weighed_levels(&mut self, cfg: &Config, hidden: &[Conv]) -> Result<Vec<String>> {
        let cues = cfg
            .pool
            .as_ref()
            .map_or(CUE_CHANNELS, ViewPool::cue_channels);
        let mut out = Vec::with_capacity(cfg.levels);
        for l in 0..cfg.levels {
            let p = format!("views.weigh.level{l}");
            let level = input_name(l); // [B, D, V, 4 + K, H, W]
            let rgb = self.slice_axis(&level, 3, 0, 3, &format!("{p}.rgb"));
            let a = self.slice_axis(&level, 3, 3, 4, &format!("{p}.alpha"));
            let k = (4 + cues) as i64;
            let cue = self.slice_axis(&level, 3, 4, k, &format!("{p}.cue")); // [B, D, V, K, H, W]
            let hw = self.shape_of(&level, 4, 6, &format!("{p}.hw"));
            let lead = self.const_i64(&[-1, cues as i64], "fold_lead");
            let shape = self.concat(&[&lead, &hw], 0, "fold_shape");
            let mut g = self.op("Reshape", &[&cue, &shape], vec![], &format!("{p}.folded")); // [B*D*V, K, H, W]
            let mut ch = cues;
            let widths = hidden.iter().map(|c| c.channels).chain([1]);
            for (i, cout) in widths.enumerate() {
                g = self.conv(&g, &format!("views.weigh.{i}"), (ch, cout), (1, 1), [0; 4])?;
                if i < hidden.len() {
                    g = self.relu(&g);
                }
                ch = cout;
            } // [B*D*V, 1, H, W]

            // 1 + tanh(S g) as 2 / (1 + exp(-2 S g)), accurate where the weight is small
            // (onnxruntime's Sigmoid and Tanh are exact to an absolute 1e-7 or so, which
            // leaves a weight of 1e-7 no significant digit).
            let scale = self.const_f32(&[], &[-2.0 * WEIGH_SCALE as f32], "weigh_scale");
            let g = self.op("Mul", &[&g, &scale], vec![], &format!("{p}.scaled"));
            let e = self.op("Exp", &[&g], vec![], &format!("{p}.exp"));
            let den = self.add_scalar(&e, 1.0, &format!("{p}.den"));
            let two = self.const_f32(&[], &[2.0], "two");
            let wk = self.op("Div", &[&two, &den], vec![], &format!("{p}.weight"));
            let bdv = self.shape_of(&level, 0, 3, &format!("{p}.bdv"));
            let one = self.const_i64(&[1], "one");
            let shape = self.concat(&[&bdv, &one, &hw], 0, "unfold_shape");
            let wk = self.op("Reshape", &[&wk, &shape], vec![], &format!("{p}.weights")); // [B, D, V, 1, H, W]
            let a = self.op("Mul", &[&a, &wk], vec![], &format!("{p}.weighed_alpha"));
            // The features family's warped maps follow the cue, and stay beside the RGBA.
            let f = cfg.pool.as_ref().map_or(0, ViewPool::feature_channels) as i64;
            let feats =
                (f > 0).then(|| self.slice_axis(&level, 3, k, k + f, &format!("{p}.features")));
            let parts: Vec<&str> = [&rgb, &a]
                .into_iter()
                .chain(feats.as_ref())
                .map(String::as_str)
                .collect();
            out.push(self.concat(&parts, 3, &format!("{p}.rgba"))); // [B, D, V, 4 (+ F), H, W]
        }
        Ok(out)
    }

    /// `ViewEncoder::forward` on every level: the towers' inputs `[B, D, 4 + 2 C_f, H, W]`
    /// and level 0's view features `[B*D*V, C_f, H_0, W_0]`.
    pub(super) fn pooled(
        &mut self,
        cfg: &Config,
        pool: &ViewPool,
    ) -> Result<(Vec<String>, String)> {
        let mut stats = Vec::with_capacity(cfg.levels);
        let mut features0 = String::new();
        for l in 0..cfg.levels {
            let p = format!("views.level{l}");
            let level = self.view_level(l); // [B, D, V, C_v, H, W]
                                            // With the cue or the source features: RGBA and the rest apart
                                            // ([B, D, V, 4, H, W], [B, D, V, K (+ F), H, W]).
            let extra = pool.encoder_view_channels() as i64;
            let (x, cue) = match extra > 4 {
                true => (
                    self.slice_axis(&level, 3, 0, 4, &format!("{p}.rgba")),
                    Some(self.slice_axis(&level, 3, 4, extra, &format!("{p}.cue"))),
                ),
                false => (level, None),
            };
            let rgb = self.slice_axis(&x, 3, 0, 3, &format!("{p}.rgb")); // [B, D, V, 3, H, W]
            let a = self.slice_axis(&x, 3, 3, 4, &format!("{p}.alpha")); // [B, D, V, 1, H, W]
            let asum = self.sum_axis(&a, 2, true, &format!("{p}.alpha_sum")); // [B, D, 1, 1, H, W]
            let den = self.add_scalar(&asum, POOL_EPS, &format!("{p}.den"));
            let mean_rgb = self.weighted_mean(&rgb, &a, &den, 2, &format!("{p}.mean_rgb")); // [B, D, 1, 3, H, W]
            let diff = self.op("Sub", &[&rgb, &mean_rgb], vec![], &format!("{p}.diff"));
            let parts: Vec<&str> = [&x, &diff]
                .into_iter()
                .chain(cue.as_ref())
                .map(String::as_str)
                .collect();
            let e_in = self.concat(&parts, 3, &format!("{p}.encoder_in")); // [B, D, V, 7 (+ K), H, W]
            let hw = self.shape_of(&x, 4, 6, &format!("{p}.hw"));
            let lead = self.const_i64(&[-1, pool.encoder_in() as i64], "fold_lead");
            let shape = self.concat(&[&lead, &hw], 0, "fold_shape");
            let mut e = self.op("Reshape", &[&e_in, &shape], vec![], &format!("{p}.folded")); // [B*D*V, 7 (+ K), H, W]
            let mut ch = pool.encoder_in();
            for (i, c) in pool.encoder.iter().enumerate() {
                e = self.conv(
                    &e,
                    &format!("views.encode.{i}"),
                    (ch, c.channels),
                    (1, 1),
                    [0; 4],
                )?;
                e = self.relu(&e);
                ch = c.channels;
            }
            if l == 0 {
                features0 = e.clone();
            }
            let bdv = self.shape_of(&x, 0, 3, &format!("{p}.bdv"));
            let cf = self.const_i64(&[ch as i64], "features");
            let shape = self.concat(&[&bdv, &cf, &hw], 0, "unfold_shape");
            let e = self.op("Reshape", &[&e, &shape], vec![], &format!("{p}.features")); // [B, D, V, C_f, H, W]
            let mean_e = self.weighted_mean(&e, &a, &den, 2, &format!("{p}.mean_e")); // [B, D, 1, C_f, H, W]
            let dev = self.op("Sub", &[&e, &mean_e], vec![], &format!("{p}.dev"));
            let sq = self.op("Mul", &[&dev, &dev], vec![], &format!("{p}.dev2"));
            let var_e = self.weighted_mean(&sq, &a, &den, 2, &format!("{p}.var_e")); // [B, D, 1, C_f, H, W]
            let one = self.add_scalar(&asum, 1.0, &format!("{p}.alpha_sum1"));
            let cover = self.op("Div", &[&asum, &one], vec![], &format!("{p}.cover")); // [B, D, 1, 1, H, W]
            let cat = self.concat(
                &[&mean_rgb, &cover, &mean_e, &var_e],
                3,
                &format!("{p}.stats6"),
            );
            let bd = self.bd.clone();
            let cp = self.const_i64(&[pool.pooled_channels() as i64], "pooled");
            let shape = self.concat(&[&bd, &cp, &hw], 0, "stats_shape");
            stats.push(self.op("Reshape", &[&cat, &shape], vec![], &format!("{p}.stats")));
            // [B, D, C_p, H, W]
        }
        Ok((stats, features0))
    }

    /// `Blend::forward` at the tile's pixels: `e0` `[B*D*V, C_f, H_0, W_0]`, `f`
    /// `[B*D, C_c, th, tw]` -> the blended source colours `[B*D, 3, th, tw]`.
    pub(super) fn blend(
        &mut self,
        cfg: &Config,
        pool: &ViewPool,
        e0: &str,
        f: &str,
    ) -> Result<String> {
        let p = cfg.pad(0) as i64;
        let cf = pool.features();
        let cc = cfg.colour.out_channels(cfg.tower_in_channels());
        let level0 = self.view_level(0);
        let v = self.shape_of(&level0, 2, 3, "views");
        let tile = self.tile.clone();
        let e = self.crop_to_tile(e0, [p, p], 0, [2, 3], "colour.blend.features"); // [B*D*V, C_f, th, tw]
                                                                                   // The first layer on [e_v, f]: its weight's two parts.
        let w = self.weight(
            "colour.blend.0.weight",
            &[self.blend_width(pool, 0), cf + cc, 1, 1],
        )?;
        let b = self.weight("colour.blend.0.bias", &[self.blend_width(pool, 0)])?;
        let we = self.slice_axis(&w, 1, 0, cf as i64, "colour.blend.0.weight_e");
        let wf = self.slice_axis(
            &w,
            1,
            cf as i64,
            (cf + cc) as i64,
            "colour.blend.0.weight_f",
        );
        let conv_attrs = || {
            vec![
                super::attr_ints("kernel_shape", &[1, 1]),
                super::attr_ints("pads", &[0; 4]),
                super::attr_ints("strides", &[1, 1]),
            ]
        };
        let ye = self.op("Conv", &[&e, &we, &b], conv_attrs(), "colour.blend.0.e"); // [B*D*V, C_0, th, tw]
        let yf = self.op("Conv", &[f, &wf], conv_attrs(), "colour.blend.0.f"); // [B*D, C_0, th, tw]
        let c0 = self.blend_width(pool, 0);
        let lead = self.const_i64(&[-1], "lead");
        let c0c = self.const_i64(&[c0 as i64], "channels");
        let shape = self.concat(&[&lead, &v, &c0c, &tile], 0, "blend_shape");
        let ye = self.op("Reshape", &[&ye, &shape], vec![], "colour.blend.0.e5"); // [B*D, V, C_0, th, tw]
        let axis1 = self.const_i64(&[1], "axis1");
        let yf = self.op("Unsqueeze", &[&yf, &axis1], vec![], "colour.blend.0.f5"); // [B*D, 1, C_0, th, tw]
        let y = self.op("Add", &[&ye, &yf], vec![], "colour.blend.0");
        let y = self.blend_rest(pool, y, c0, &tile)?;
        let one = self.const_i64(&[1], "one");
        let shape = self.concat(&[&lead, &v, &one, &tile], 0, "logit_shape");
        let logits = self.op("Reshape", &[&y, &shape], vec![], "colour.blend.logits"); // [B*D, V, 1, th, tw]
        let inv = self.const_f32(&[], &[(1.0 / BLEND_LOGIT_BOUND) as f32], "inv_bound");
        let bound = self.const_f32(&[], &[BLEND_LOGIT_BOUND as f32], "bound");
        let scaled = self.op("Mul", &[&logits, &inv], vec![], "colour.blend.scaled");
        let t = self.op("Tanh", &[&scaled], vec![], "colour.blend.tanh");
        let logits = self.op("Mul", &[&t, &bound], vec![], "colour.blend.bounded");
        // The sources' RGBA (and cue) at the tile: [B*D, V, C_v, th, tw].
        let x = self.crop_to_tile(&level0, [p, p], 0, [4, 5], "colour.blend.rgba6");
        let cv = self.const_i64(&[pool.encoder_view_channels() as i64], "view_channels");
        let shape = self.concat(&[&lead, &v, &cv, &tile], 0, "rgba_shape");
        let x = self.op("Reshape", &[&x, &shape], vec![], "colour.blend.rgba"); // [B*D, V, C_v, th, tw]
        let rgb = self.slice_axis(&x, 2, 0, 3, "colour.blend.rgb");
        let a = self.slice_axis(&x, 2, 3, 4, "colour.blend.alpha");
        let ex = self.op("Exp", &[&logits], vec![], "colour.blend.exp");
        let ex = self.op("Mul", &[&ex, &a], vec![], "colour.blend.exp_alpha"); // [B*D, V, 1, th, tw]
        let s = self.sum_axis(&ex, 1, true, "colour.blend.sum");
        let den = self.add_scalar(&s, BLEND_EPS, "colour.blend.den");
        let wts = self.op("Div", &[&ex, &den], vec![], "colour.blend.weights");
        let wrgb = self.op("Mul", &[&rgb, &wts], vec![], "colour.blend.weighted");
        Ok(self.sum_axis(&wrgb, 1, false, "colour.blend.colour")) // [B*D, 3, th, tw]
    }

    /// The blend's layers after the first on its output `y` `[B*D, V, C_0, th, tw]`:
    /// `[B*D*V, 1, th, tw]` (`y` itself when the first layer is the logit).
    fn blend_rest(
        &mut self,
        pool: &ViewPool,
        mut y: String,
        c0: usize,
        tile: &str,
    ) -> Result<String> {
        let last = pool.blend.len();
        if last == 0 {
            return Ok(y);
        }
        y = self.relu(&y);
        let lead = self.const_i64(&[-1, c0 as i64], "fold_lead");
        let shape = self.concat(&[&lead, tile], 0, "fold_shape");
        y = self.op("Reshape", &[&y, &shape], vec![], "colour.blend.folded"); // [B*D*V, C_0, th, tw]
        let mut ch = c0;
        for i in 1..=last {
            let cout = self.blend_width(pool, i);
            y = self.conv(&y, &format!("colour.blend.{i}"), (ch, cout), (1, 1), [0; 4])?;
            if i < last {
                y = self.relu(&y);
            }
            ch = cout;
        }
        Ok(y)
    }

    /// Output channels of blend layer `i` (the last is the 1-channel logit).
    fn blend_width(&self, pool: &ViewPool, i: usize) -> usize {
        pool.blend.get(i).map_or(1, |c| c.channels)
    }
}
