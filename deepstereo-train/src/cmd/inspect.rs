//! `deepstereo inspect`: what a scene reader made of a directory: its format, near/far
//! and every view's size, intrinsics, centre and world-to-camera `R` (row-major), `t`.

use super::args::SceneArgs;
use crate::cmd::support::camera_json::scene_json;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub scene: SceneArgs,
    /// Print JSON (`format`, `near`, `far` (`null` for a plane at infinity), `views: [{name,
    /// width, height, fx, fy, cx, cy, R (3x3 row-major, world-to-camera, OpenCV axes), t}]`)
    /// instead of text. A rolling-shutter view adds `rolling_shutter: {R_start, t_start,
    /// R_end, t_end, time_origin, time_per_pixel}` (the pixel `(u, v)` is exposed at time
    /// `time_origin + time_per_pixel . (u, v)`, between the start pose at 0 and the end
    /// pose at 1); its `R`, `t` are then the pose at the image centre's time.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: Args) -> anyhow::Result<()> {
    let scene = args.scene.load()?;
    if args.json {
        let out = scene_json(&scene);
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!("scene   {}", scene.root.display());
    println!("format  {}", scene.format.name());
    println!("views   {}", scene.views.len());
    let source = match scene.bounds_source {
        deepstereo_core::scene::BoundsSource::Auto => {
            format!("automatic, from {} matched points", scene.points.len())
        }
        s => s.describe().to_string(),
    };
    println!("near    {:.6}  far {}  ({source})", scene.near, scene.far);
    for (i, v) in scene.views.iter().enumerate() {
        let k = &v.camera.intrinsics;
        let c = v.camera.pose.centre();
        println!(
            "{i:4} {:<24} {}x{}  f=({:.2},{:.2}) c=({:.2},{:.2})  centre=({:.4},{:.4},{:.4})",
            v.name, k.width, k.height, k.fx, k.fy, k.cx, k.cy, c.x, c.y, c.z
        );
        if let Some(rs) = &v.camera.rolling_shutter {
            let (c0, c1) = (rs.start.centre(), rs.end.centre());
            println!(
                "     rolling shutter: t(u,v) = {:.6} + {:.3e} u + {:.3e} v; centre at t=0 ({:.4},{:.4},{:.4}), t=1 ({:.4},{:.4},{:.4})",
                rs.time_origin, rs.time_per_pixel.x, rs.time_per_pixel.y, c0.x, c0.y, c0.z, c1.x, c1.y, c1.z
            );
        }
        let (r, t) = (v.camera.pose.rotation, v.camera.pose.translation);
        let row = |i: usize| format!("{:.6} {:.6} {:.6}", r.x_axis[i], r.y_axis[i], r.z_axis[i]);
        println!(
            "     R=[{}; {}; {}]  t=({:.6},{:.6},{:.6})",
            row(0),
            row(1),
            row(2),
            t.x,
            t.y,
            t.z
        );
    }
    Ok(())
}
