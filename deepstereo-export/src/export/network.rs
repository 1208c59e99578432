//! The network's steps after the view pooling, as graph nodes: the towers, the selection
//! head and the colours, each following `model.rs`.

use super::{attr_int, attr_ints, attr_str, input_name, Graph};
use crate::error::Result;
use deepstereo_core::config::{Config, Conv, TowerConfig};

impl Graph<'_> {
    /// Valid `k x k` convolutions `prefix.{i}`, each followed by ReLU, on `x` of `cin`
    /// channels.
    pub(super) fn conv_relu_chain(
        &mut self,
        x: &str,
        prefix: &str,
        cin: usize,
        convs: &[Conv],
    ) -> Result<String> {
        let (mut x, mut ch) = (x.to_string(), cin);
        for (i, c) in convs.iter().enumerate() {
            x = self.conv(
                &x,
                &format!("{prefix}.{i}"),
                (ch, c.channels),
                (c.kernel, c.kernel),
                [0; 4],
            )?;
            x = self.relu(&x);
            ch = c.channels;
        }
        Ok(x)
    }

    /// `x[..., starts[i] .. starts[i] + tile[i] + extra, ...]` on `axes` (two of them), the
    /// tile size read from the graph: `narrow(axes[0], s0, th + extra).narrow(axes[1], s1, tw + extra)`.
    pub(super) fn crop_to_tile(
        &mut self,
        x: &str,
        starts: [i64; 2],
        extra: i64,
        axes: [i64; 2],
        hint: &str,
    ) -> String {
        let s = self.const_i64(&starts, "starts");
        let add = self.const_i64(&[starts[0] + extra, starts[1] + extra], "end_offset");
        let tile = self.tile.clone();
        let ends = self.op("Add", &[&tile, &add], vec![], "ends");
        let ax = self.const_i64(&axes, "axes");
        self.op("Slice", &[x, &s, &ends, &ax], vec![], hint)
    }

    /// `Tower::forward` of `model.rs`: `inputs[l]` `[N, C_in, H_l, W_l]` -> `[N, C, th, tw]`.
    pub(super) fn tower(
        &mut self,
        t: &TowerConfig,
        prefix: &str,
        inputs: &[String],
        cin: usize,
    ) -> Result<String> {
        let rf = t.merge_reduction();
        let mut feats = Vec::with_capacity(t.levels);
        for (l, input) in inputs.iter().enumerate().take(t.levels) {
            let mut x =
                self.conv_relu_chain(input, &format!("{prefix}.levels.{l}"), cin, &t.level_convs)?;
            if l > 0 {
                // upsample_nearest(x, 2^l): exact nearest with integer factors.
                let s = (1u32 << l) as f32;
                let scales = self.const_f32(&[4], &[1.0, 1.0, s, s], "scales");
                let attrs = vec![
                    attr_str("mode", "nearest"),
                    attr_str("coordinate_transformation_mode", "asymmetric"),
                    attr_str("nearest_mode", "floor"),
                ];
                x = self.op(
                    "Resize",
                    &[&x, "", &scales],
                    attrs,
                    &format!("{prefix}.levels.{l}.upsample"),
                );
            }
            // x.narrow(2, off, th + rf).narrow(3, off, tw + rf)
            let off = t.upsample_crop(l) as i64;
            x = self.crop_to_tile(
                &x,
                [off, off],
                rf as i64,
                [2, 3],
                &format!("{prefix}.levels.{l}.crop"),
            );
            feats.push(x);
        }
        let mut x = if feats.len() == 1 {
            feats.remove(0)
        } else {
            let refs: Vec<&str> = feats.iter().map(String::as_str).collect();
            self.op(
                "Concat",
                &refs,
                vec![attr_int("axis", 1)],
                &format!("{prefix}.concat"),
            )
        };
        x = self.conv_relu_chain(
            &x,
            &format!("{prefix}.merge"),
            t.level_channels(cin) * t.levels,
            &t.merge_convs,
        )?;
        Ok(x)
    }

    /// `[B, D, C, h, w]` -> `[B*D, C, h, w]` (`C` fixed, `h`, `w` read from `x`).
    pub(super) fn fold_planes(&mut self, x: &str, c: usize, hint: &str) -> String {
        let lead = self.const_i64(&[-1, c as i64], "fold_lead");
        let hw = self.op("Shape", &[x], vec![attr_int("start", 3)], "fold_hw");
        let shape = self.op(
            "Concat",
            &[&lead, &hw],
            vec![attr_int("axis", 0)],
            "fold_shape",
        );
        self.op("Reshape", &[x, &shape], vec![], hint)
    }

    /// `folded(t)` of `DeepStereo::forward`: each level the tower reads (`levels[l]`,
    /// `[B, D, cin, H_l, W_l]`), cropped to its footprint and with planes folded into the
    /// batch.
    pub(super) fn folded(
        &mut self,
        cfg: &Config,
        t: &TowerConfig,
        prefix: &str,
        levels: &[String],
        cin: usize,
    ) -> Vec<String> {
        (0..t.levels)
            .map(|l| {
                let off = (cfg.pad(l) - t.pad(l)) as i64;
                let mut x = levels[l].clone();
                if off > 0 {
                    // x.narrow(3, off, h - 2 off).narrow(4, off, w - 2 off)
                    let s = self.const_i64(&[off, off], "starts");
                    let e = self.const_i64(&[-off, -off], "ends");
                    let ax = self.const_i64(&[3, 4], "axes");
                    x = self.op(
                        "Slice",
                        &[&x, &s, &e, &ax],
                        vec![],
                        &format!("{prefix}.input{l}.crop"),
                    );
                }
                self.fold_planes(&x, cin, &format!("{prefix}.input{l}.folded"))
            })
            .collect()
    }

    /// `DeepStereo::forward`; returns the names of `image` and `selection`.
    pub(super) fn forward(&mut self, cfg: &Config) -> Result<(String, String)> {
        let cin = cfg.tower_in_channels();
        // The towers' inputs: the sweep itself, or the pooled statistics.
        let (towers_in, features) = match &cfg.pool {
            Some(pool) => {
                if let Some(hidden) = &pool.weigh {
                    self.view_levels = self.weighed_levels(cfg, hidden)?;
                }
                let (stats, features) = self.pooled(cfg, pool)?;
                (stats, Some(features))
            }
            None => ((0..cfg.levels).map(input_name).collect(), None),
        };

        let selection = self.selection(cfg, &towers_in, cin)?; // [B, D, th, tw]
        let colours = self.colours(cfg, &towers_in, features.as_deref(), cin)?; // [B*D, 3, th, tw]
        let image = self.composite(&colours, &selection); // [B, 3, th, tw]
        Ok((image, selection))
    }

    /// Selection tower, the depth layers and the softmax over planes: `[B, D, th, tw]`.
    pub(super) fn selection(
        &mut self,
        cfg: &Config,
        towers_in: &[String],
        cin: usize,
    ) -> Result<String> {
        let bd = self.bd.clone();
        let tile = self.tile.clone();
        let inputs = self.folded(cfg, &cfg.select, "select", towers_in, cin);
        let s = self.tower(&cfg.select, "select", &inputs, cin)?; // [B*D, C, th, tw]
        let c = cfg.select.out_channels(cin);
        let tail = self.const_i64(&[c as i64, -1], "select_tail");
        let shape = self.op(
            "Concat",
            &[&bd, &tail],
            vec![attr_int("axis", 0)],
            "select_shape",
        );
        let x = self.op("Reshape", &[&s, &shape], vec![], "select.unfold"); // [B, D, C, th*tw]
        let mut x = self.op(
            "Transpose",
            &[&x],
            vec![attr_ints("perm", &[0, 2, 1, 3])],
            "select.transpose",
        ); // [B, C, D, th*tw]
        let last = cfg.depth_convs.len() - 1;
        let mut ch = c;
        for (i, conv) in cfg.depth_convs.iter().enumerate() {
            // conv(pad_with_zeros(x, 2, p, p)): zero padding along depth only.
            let p = (conv.kernel / 2) as i64;
            x = self.conv(
                &x,
                &format!("select.depth.{i}"),
                (ch, conv.channels),
                (conv.kernel, 1),
                [p, 0, p, 0],
            )?;
            if i < last {
                x = self.relu(&x);
            }
            ch = conv.channels;
        }
        let x = self.op("Tanh", &[&x], vec![], "select.tanh");
        let log_scale = self.weight("select.log_scale", &[1])?;
        let scale = self.op("Exp", &[&log_scale], vec![], "select.scale");
        let logits = self.op("Mul", &[&x, &scale], vec![], "select.logits"); // [B, 1, D, th*tw]
        let sel = self.op(
            "Softmax",
            &[&logits],
            vec![attr_int("axis", 2)],
            "select.softmax",
        );
        let sel_shape = self.op(
            "Concat",
            &[&bd, &tile],
            vec![attr_int("axis", 0)],
            "selection_shape",
        );
        Ok(self.op("Reshape", &[&sel, &sel_shape], vec![], "selection")) // [B, D, th, tw]
    }

    /// Colour tower (with the skip input), its output layer and, pooled, the blend of the
    /// sources' colours by the view features: `[B*D, 3, th, tw]`.
    pub(super) fn colours(
        &mut self,
        cfg: &Config,
        towers_in: &[String],
        features: Option<&str>,
        cin: usize,
    ) -> Result<String> {
        let inputs = self.folded(cfg, &cfg.colour, "colour", towers_in, cin);
        let mut f = self.tower(&cfg.colour, "colour", &inputs, cin)?; // [B*D, C, th, tw]
        let mut cout_in = cfg.colour.out_channels(cin);
        let blended = match (&cfg.pool, features) {
            (Some(pool), Some(e)) => Some(self.blend(cfg, pool, e, &f)?), // [B*D, 3, th, tw]
            _ => None,
        };
        if cfg.colour_skip {
            let p = cfg.pad(0) as i64;
            let centre = self.crop_to_tile(&input_name(0), [p, p], 0, [3, 4], "colour.centre");
            let centre = self.fold_planes(&centre, cfg.in_channels(), "colour.centre.folded"); // [B*D, 4V, th, tw]
            f = self.op(
                "Concat",
                &[&f, &centre],
                vec![attr_int("axis", 1)],
                "colour.skip",
            );
            cout_in += cin;
        }
        let mut colours = self.conv(&f, "colour.out", (cout_in, 3), (1, 1), [0; 4])?; // [B*D, 3, th, tw]
        if let Some(blended) = blended {
            colours = self.op("Add", &[&blended, &colours], vec![], "colour.sum");
        }
        Ok(colours)
    }

    /// The rendered colour `sum over D of s * c`: colours `[B*D, 3, th, tw]` and selection
    /// `[B, D, th, tw]` -> `[B, 3, th, tw]`.
    pub(super) fn composite(&mut self, colours: &str, selection: &str) -> String {
        let bd = self.bd.clone();
        let tile = self.tile.clone();
        let three = self.const_i64(&[3], "three");
        let col_shape = self.op(
            "Concat",
            &[&bd, &three, &tile],
            vec![attr_int("axis", 0)],
            "colours_shape",
        );
        let colours = self.op("Reshape", &[colours, &col_shape], vec![], "colours"); // [B, D, 3, th, tw]
        let axis2 = self.const_i64(&[2], "axis2");
        let sel5 = self.op("Unsqueeze", &[selection, &axis2], vec![], "selection5"); // [B, D, 1, th, tw]
        let weighted = self.op("Mul", &[&colours, &sel5], vec![], "weighted"); // [B, D, 3, th, tw]
        let axis1 = self.const_i64(&[1], "axis1");
        self.op(
            "ReduceSum",
            &[&weighted, &axis1],
            vec![attr_int("keepdims", 0)],
            "image",
        ) // [B, 3, th, tw]
    }
}
