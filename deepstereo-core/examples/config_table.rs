//! Prints the layer tables of the presets as markdown (for the README):
//! `cargo run --release -p deepstereo-core --example config_table`.

use deepstereo_core::config::Config;

fn main() {
    for cfg in [
        Config::tiny(),
        Config::nviews(),
        Config::nviews_disagree(),
        Config::nviews_features(),
        Config::paper(),
    ] {
        println!(
            "\n**{}**: {} views, {} planes, {} levels, {}x{} output tile from {}x{} level-0 input; \
             receptive field {} px; {} parameters; {:.2} M multiply-adds per output pixel\n",
            cfg.name, cfg.views, cfg.planes, cfg.levels, cfg.tile, cfg.tile,
            cfg.input_size(0, cfg.tile), cfg.input_size(0, cfg.tile), cfg.receptive_field(),
            cfg.parameters(), cfg.macs_per_pixel() / 1e6
        );
        println!(
            "| layer | kernel | in | out | params | MACs / output px |\n|---|---|---|---|---|---|"
        );
        for l in cfg.layers() {
            println!(
                "| `{}` | {} | {} | {} | {} | {:.0} |",
                l.name, l.kernel, l.in_channels, l.out_channels, l.params, l.macs_per_pixel
            );
        }
    }
}
