//! The library's enums as command-line choices: the names flags take and the help
//! `--help` prints for each. The library types carry no clap derive; this maps to them.

use crate::cmd::support::colmap_run::Matcher;
use crate::rendering::models::BackendKind;
use crate::rendering::PlaneSpan;
use crate::training::optim::OptimizerKind;
use crate::training::Loss;
use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};

/// A library enum offered as a command-line choice.
pub trait Choice: Copy + Send + Sync + 'static {
    /// Every value, in the order `--help` lists them.
    const ALL: &'static [Self];
    /// The name a flag takes.
    fn name(self) -> &'static str;
    /// What `--help` says of it (empty: nothing).
    fn help(self) -> &'static str {
        ""
    }
}

/// clap's parser of a [`Choice`]: one of its names, listed with their help.
pub fn choice<T: Choice>() -> impl TypedValueParser<Value = T> {
    let values = T::ALL.iter().map(|v| match v.help() {
        "" => PossibleValue::new(v.name()),
        h => PossibleValue::new(v.name()).help(h),
    });
    PossibleValuesParser::new(values).try_map(|s: String| {
        T::ALL
            .iter()
            .copied()
            .find(|v| v.name() == s)
            .ok_or_else(|| format!("unknown value '{s}'"))
    })
}

impl Choice for BackendKind {
    const ALL: &'static [Self] = &[BackendKind::Candle, BackendKind::Ort];
    fn name(self) -> &'static str {
        match self {
            BackendKind::Candle => "candle",
            BackendKind::Ort => "ort",
        }
    }
}

impl Choice for OptimizerKind {
    const ALL: &'static [Self] = &[OptimizerKind::Adagrad, OptimizerKind::Adam];
    fn name(self) -> &'static str {
        match self {
            OptimizerKind::Adagrad => "adagrad",
            OptimizerKind::Adam => "adam",
        }
    }
}

impl Choice for Loss {
    const ALL: &'static [Self] = &[Loss::L1, Loss::L2];
    fn name(self) -> &'static str {
        match self {
            Loss::L1 => "l1",
            Loss::L2 => "l2",
        }
    }
    fn help(self) -> &'static str {
        match self {
            Loss::L1 => "Mean absolute error (the paper's)",
            Loss::L2 => "Mean squared error",
        }
    }
}

impl Choice for Matcher {
    const ALL: &'static [Self] = &[Matcher::Exhaustive, Matcher::Sequential];
    fn name(self) -> &'static str {
        match self {
            Matcher::Exhaustive => "exhaustive",
            Matcher::Sequential => "sequential",
        }
    }
    fn help(self) -> &'static str {
        match self {
            Matcher::Exhaustive => "Every pair (small sets)",
            Matcher::Sequential => "Each image with the next few in name order (video-like sets)",
        }
    }
}

impl Choice for PlaneSpan {
    const ALL: &'static [Self] = &[PlaneSpan::Scene, PlaneSpan::View];
    fn name(self) -> &'static str {
        match self {
            PlaneSpan::Scene => "scene",
            PlaneSpan::View => "view",
        }
    }
    fn help(self) -> &'static str {
        match self {
            PlaneSpan::Scene => "Between the scene's near and far",
            PlaneSpan::View => {
                "As many planes over the depths the camera sees: between the nearest and \
                 farthest of the scene's sparse points in its view (or its sources' per-view \
                 bounds), widened as pruning widens that range, so every plane samples depths \
                 the view holds. The scene's planes where neither says anything"
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each choice's names are distinct, and the serialized name (where the type is
    /// written to JSON) is the flag's.
    #[test]
    fn every_choice_parses_its_own_names() {
        fn check<T: Choice + PartialEq + std::fmt::Debug>() {
            let cmd = clap::Command::new("t")
                .arg(clap::Arg::new("x").long("x").value_parser(choice::<T>()));
            for &v in T::ALL {
                let m = cmd
                    .clone()
                    .try_get_matches_from(["t", "--x", v.name()])
                    .expect("parses");
                assert_eq!(m.get_one::<T>("x"), Some(&v));
            }
            assert!(cmd.try_get_matches_from(["t", "--x", "bogus"]).is_err());
        }
        check::<BackendKind>();
        check::<OptimizerKind>();
        check::<Loss>();
        check::<Matcher>();
        check::<PlaneSpan>();
        let json = |v: &dyn erased::Ser| v.json();
        assert_eq!(json(&Loss::L2), "\"l2\"");
        assert_eq!(json(&OptimizerKind::Adam), "\"adam\"");
        assert_eq!(json(&BackendKind::Ort), "\"ort\"");
        assert_eq!(json(&PlaneSpan::View), "\"view\"");
    }

    mod erased {
        pub trait Ser {
            fn json(&self) -> String;
        }
        impl<T: serde::Serialize> Ser for T {
            fn json(&self) -> String {
                serde_json::to_string(self).unwrap_or_default()
            }
        }
    }
}
