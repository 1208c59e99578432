//! [`Config::validate`]: the checks of a config's internal consistency, in order, each
//! returning a message naming the problem.

use super::*;

impl Config {
    /// Checks internal consistency; returns a message naming the problem.
    pub fn validate(&self) -> Result<(), String> {
        self.check_sizes()?;
        for (name, t) in [("select", &self.select), ("colour", &self.colour)] {
            self.check_tower(name, t)?;
        }
        if let Some(pool) = &self.pool {
            check_pool(pool, self.colour_skip)?;
        }
        if self.depth_convs.last().map(|c| c.channels) != Some(1) {
            return Err("the last depth conv must have 1 channel".into());
        }
        if self.tile == 0 || !self.tile.is_multiple_of(self.tile_align()) {
            return Err(format!(
                "tile {} must be a positive multiple of {}",
                self.tile,
                self.tile_align()
            ));
        }
        Ok(())
    }

    /// Views, planes, tile, list lengths and levels within their bounds.
    fn check_sizes(&self) -> Result<(), String> {
        if self.views == 0 || self.planes == 0 {
            return Err("views and planes must be positive".into());
        }
        if let Some(r) = self.render_planes.filter(|&r| r == 0 || r > MAX_PLANES) {
            return Err(format!("render_planes must be 1 to {MAX_PLANES}, got {r}"));
        }
        if self.views > MAX_VIEWS || self.planes > MAX_PLANES || self.tile > MAX_TILE {
            return Err(format!(
                "views {}, planes {} and tile {} must be at most {MAX_VIEWS}, {MAX_PLANES} and {MAX_TILE}",
                self.views, self.planes, self.tile
            ));
        }
        let lists = [
            &self.select.level_convs,
            &self.select.merge_convs,
            &self.depth_convs,
        ];
        if lists
            .iter()
            .chain([&self.colour.level_convs, &self.colour.merge_convs].iter())
            .any(|l| l.len() > MAX_CONVS)
        {
            return Err(format!("at most {MAX_CONVS} convolutions per list"));
        }
        if self.levels == 0 || self.levels > 6 {
            return Err(format!("levels must be 1..=6, got {}", self.levels));
        }
        Ok(())
    }

    /// Tower `name`'s levels, and its convolutions' kernels and channels (the selection
    /// tower's with the depth convolutions).
    fn check_tower(&self, name: &str, t: &TowerConfig) -> Result<(), String> {
        if t.levels == 0 || t.levels > self.levels {
            return Err(format!(
                "{name}.levels must be 1..={}, got {}",
                self.levels, t.levels
            ));
        }
        let convs = t.level_convs.iter().chain(&t.merge_convs);
        for conv in convs.chain(if name == "select" {
            self.depth_convs.iter()
        } else {
            [].iter()
        }) {
            if conv.kernel % 2 == 0 || conv.channels == 0 {
                return Err(format!(
                    "{name}: kernels must be odd and channels positive, got {conv:?}"
                ));
            }
            if conv.kernel > MAX_KERNEL || conv.channels > MAX_CHANNELS {
                return Err(format!(
                    "{name}: kernels must be at most {MAX_KERNEL} and channels at most {MAX_CHANNELS}, got {conv:?}"
                ));
            }
        }
        Ok(())
    }
}

/// The pool's layers and options, of a config whose `colour_skip` is given.
fn check_pool(pool: &ViewPool, colour_skip: bool) -> Result<(), String> {
    let weigh = pool.weigh.as_deref().unwrap_or_default();
    for conv in pool.encoder.iter().chain(&pool.blend).chain(weigh) {
        if conv.kernel != 1 || conv.channels == 0 || conv.channels > MAX_CHANNELS {
            return Err(format!(
                "pool: encoder, blend and weigh layers must be 1x1 with 1 to {MAX_CHANNELS} channels, got {conv:?}"
            ));
        }
    }
    if pool.cue && pool.weigh.is_some() {
        return Err(
            "pool: cue and weigh are exclusive (the cue enters the encoder, or weighs the views)"
                .into(),
        );
    }
    let lists = [&pool.encoder, &pool.blend];
    if lists.iter().any(|l| l.len() > MAX_CONVS) || weigh.len() > MAX_CONVS {
        return Err(format!("at most {MAX_CONVS} convolutions per list"));
    }
    check_gates(pool)?;
    if colour_skip {
        return Err("pool: colour_skip must be false (the blend feeds the source colours)".into());
    }
    if let Some(f) = &pool.features {
        f.validate()?;
    }
    Ok(())
}

/// The pool's falloff, agreement gate and disagreement cue within their ranges.
fn check_gates(pool: &ViewPool) -> Result<(), String> {
    if let Some(f) = pool.falloff {
        if !(1..=MAX_VIEWS).contains(&f.full) || !(1..=MAX_FALLOFF_POWER).contains(&f.power) {
            return Err(format!(
                "pool.falloff: full must be 1 to {MAX_VIEWS} and power 1 to {MAX_FALLOFF_POWER}, got {f:?}"
            ));
        }
    }
    if let Some(a) = pool.agree {
        let (lo, hi) = AGREE_SIGMA_RANGE;
        if !((1..=MAX_VIEWS).contains(&a.near) && (lo..=hi).contains(&a.sigma)) {
            return Err(format!(
                "pool.agree: near must be 1 to {MAX_VIEWS} and sigma {lo} to {hi}, got {a:?}"
            ));
        }
    }
    if let Some(d) = pool.disagree {
        if !(1..=MAX_VIEWS).contains(&d.near) {
            return Err(format!(
                "pool.disagree: near must be 1 to {MAX_VIEWS}, got {}",
                d.near
            ));
        }
        if pool.weigh.is_none() {
            return Err("pool.disagree needs pool.weigh (the view weights read it)".into());
        }
    }
    Ok(())
}
