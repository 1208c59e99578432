//! Kill training with SIGKILL mid-run; `--resume` continues with identical losses.

use anyhow::{ensure, Result};
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_deepstereo");

fn args(out: &Path) -> Vec<String> {
    let s = |x: &str| x.to_string();
    vec![
        s("train"),
        s("--synthetic"),
        s("3"),
        s("--synth-size"),
        s("64x48"),
        s("--synth-views"),
        s("6"),
        s("--steps"),
        s("8"),
        s("--batch"),
        s("2"),
        s("--checkpoint-every"),
        s("2"),
        s("--log-every"),
        s("1"),
        s("--validate-every"),
        s("4"),
        s("--val-scenes"),
        s("1"),
        s("--val-batches"),
        s("1"),
        s("--no-progress"),
        s("--optimizer"),
        s("adam"),
        s("--lr"),
        s("1e-3"),
        s("--seed"),
        s("3"),
        s("--out"),
        out.display().to_string(),
    ]
}

/// Sets the value after `flag` (one of [`args`]' options) to `value`.
fn set(args: &mut [String], flag: &str, value: &str) -> Result<()> {
    let i = args.iter().position(|x| x == flag);
    let Some(slot) = i.and_then(|i| args.get_mut(i + 1)) else {
        anyhow::bail!("no option {flag} to set");
    };
    *slot = value.to_string();
    Ok(())
}

/// Runs the binary with `args` and requires it to succeed (its stderr in the error).
fn run_ok(args: &[String]) -> Result<()> {
    let o = Command::new(BIN).args(args).output()?;
    ensure!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    Ok(())
}

/// Runs the resume `args` and requires it to fail as a change of options (`what` changed).
fn refused_as_other_options(args: &[String], what: &str) -> Result<()> {
    let o = Command::new(BIN).args(args).output()?;
    ensure!(!o.status.success(), "resume with another {what} must fail");
    ensure!(String::from_utf8_lossy(&o.stderr).contains("different options"));
    Ok(())
}

fn losses(out: &Path) -> Result<Vec<(u64, f64)>> {
    let text = std::fs::read_to_string(out.join("log.jsonl"))?;
    text.lines()
        .map(|l| {
            let v: serde_json::Value = serde_json::from_str(l)?;
            Ok((
                v["step"].as_u64().unwrap_or(0),
                v["loss"].as_f64().unwrap_or(f64::NAN),
            ))
        })
        .collect()
}

#[test]
fn sigkill_then_resume_gives_identical_losses() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let st = Command::new(BIN)
        .args(args(&a))
        .stderr(Stdio::null())
        .status()?;
    ensure!(st.success(), "uninterrupted run failed");
    let mut child = Command::new(BIN)
        .args(args(&b))
        .stderr(Stdio::null())
        .spawn()?;
    let t0 = Instant::now();
    loop {
        let n = losses(&b).map(|l| l.len()).unwrap_or(0);
        if n >= 5 || t0.elapsed() > Duration::from_secs(300) {
            break;
        }
        if child.try_wait()?.is_some() {
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill()?; // SIGKILL on Unix
    child.wait()?;
    let before = losses(&b)?.len();
    let mut resume = args(&b);
    resume.push("--resume".into());
    let st = Command::new(BIN)
        .args(&resume)
        .stderr(Stdio::null())
        .status()?;
    ensure!(st.success(), "resumed run failed");
    let (la, lb) = (losses(&a)?, losses(&b)?);
    println!("killed after {before} log lines; uninterrupted {la:?}\nresumed {lb:?}");
    // Identical up to float summation order: candle's CPU kernels occasionally change the
    // last bit of a reduction between runs (seen on the loss only, never on the weights:
    // the losses after such a step agree exactly). A wrong restore of weights, optimizer
    // state or data order changes losses in the second or third digit.
    ensure!(la.len() == lb.len(), "log lengths differ:\n{la:?}\n{lb:?}");
    for ((sa, a), (sb, b)) in la.iter().zip(&lb) {
        ensure!(
            sa == sb && (a - b).abs() <= 1e-6 * a.abs(),
            "losses differ at step {sa}:\n{la:?}\n{lb:?}"
        );
    }
    ensure!(la.len() == 8, "expected 8 log lines, got {}", la.len());
    Ok(())
}

#[test]
fn resume_refuses_different_options() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let out = dir.path().join("r");
    let mut a = args(&out);
    set(&mut a, "--steps", "2")?;
    run_ok(&a)?;
    let mut b = args(&out);
    b.push("--resume".into());
    set(&mut b, "--seed", "4")?;
    refused_as_other_options(&b, "seed")
}

#[test]
fn the_loss_is_a_run_option_and_a_resume_must_keep_it() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let out = dir.path().join("l2");
    let mut a = args(&out);
    set(&mut a, "--steps", "2")?;
    a.extend(["--loss".into(), "l2".into()]);
    run_ok(&a)?;
    let l = losses(&out)?;
    ensure!(l.len() == 2 && l.iter().all(|(_, v)| v.is_finite() && *v >= 0.0));
    // The same run with L1 logs other losses from the same batches.
    let out1 = dir.path().join("l1");
    let mut b = args(&out1);
    set(&mut b, "--steps", "2")?;
    run_ok(&b)?;
    ensure!(
        losses(&out1)?[0].1 != l[0].1,
        "L1 and L2 logged the same first loss"
    );
    // Resuming the L2 run without --loss (L1) is a change of options.
    let mut c = args(&out);
    set(&mut c, "--steps", "3")?;
    c.push("--resume".into());
    refused_as_other_options(&c, "loss")?;
    c.extend(["--loss".into(), "l2".into()]);
    run_ok(&c)?;
    ensure!(losses(&out)?.len() == 3);
    // An unknown loss is refused by name.
    let mut d = args(&dir.path().join("bad"));
    d.extend(["--loss".into(), "huber".into()]);
    let o = Command::new(BIN).args(&d).output()?;
    ensure!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("huber"));
    Ok(())
}

#[test]
fn a_resume_may_add_a_learning_rate_schedule_and_the_log_follows_it() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let out = dir.path().join("s");
    let mut a = args(&out);
    set(&mut a, "--steps", "4")?; // constant rate
    run_ok(&a)?;
    let mut b = args(&out);
    b.extend(
        [
            "--resume",
            "--lr-schedule",
            "cosine:4-6",
            "--lr-final",
            "0.1",
        ]
        .map(String::from),
    );
    let res = Command::new(BIN).args(&b).output()?;
    ensure!(
        res.status.success(),
        "{}",
        String::from_utf8_lossy(&res.stderr)
    );
    ensure!(String::from_utf8_lossy(&res.stderr).contains("learning-rate schedule changed"));
    let text = std::fs::read_to_string(out.join("log.jsonl"))?;
    let lrs: Vec<f64> = text
        .lines()
        .map(|l| {
            serde_json::from_str::<serde_json::Value>(l)
                .map(|v| v["lr"].as_f64().unwrap_or(f64::NAN))
        })
        .collect::<Result<_, _>>()?;
    // Steps 1-4 at 1e-3; the updates after 4 and 5 completed steps at 1e-3 and
    // (0.1 + 0.9 * (1 + cos(pi / 2)) / 2) * 1e-3; then 1e-4 from 6 on.
    let want = [1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 0.55e-3, 1e-4, 1e-4];
    ensure!(lrs.len() == want.len(), "{lrs:?}");
    for (got, w) in lrs.iter().zip(want) {
        ensure!((got - w).abs() < 1e-12, "{lrs:?} against {want:?}");
    }
    // A bad schedule is refused by name.
    let mut c = args(&dir.path().join("t"));
    c.extend(["--lr-schedule", "cosine:9-3"].map(String::from));
    let res = Command::new(BIN).args(&c).output()?;
    ensure!(!res.status.success());
    ensure!(String::from_utf8_lossy(&res.stderr).contains("--lr-schedule"));
    Ok(())
}

/// The tensors of a safetensors file as f32 vectors, by name.
fn tensors(path: &Path) -> Result<std::collections::BTreeMap<String, Vec<f32>>> {
    let bytes = std::fs::read(path)?;
    let st = safetensors::SafeTensors::deserialize(&bytes)?;
    Ok(st
        .tensors()
        .into_iter()
        .map(|(name, v)| {
            let data = v
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            (name, data)
        })
        .collect())
}

fn max_diff(a: &Path, b: &Path) -> Result<f32> {
    let (ta, tb) = (tensors(a)?, tensors(b)?);
    ensure!(ta.keys().eq(tb.keys()), "different tensor names");
    Ok(ta
        .values()
        .zip(tb.values())
        .flat_map(|(x, y)| x.iter().zip(y).map(|(p, q)| (p - q).abs()))
        .fold(0.0, f32::max))
}

/// `--init` starts from a model's weights: one step at a negligible rate leaves them as
/// they were (a seeded start is far from them); a model of another shape is refused.
#[test]
fn init_starts_from_a_models_weights_and_refuses_a_mismatch() -> Result<()> {
    let dir = tempfile::tempdir()?;
    let (a_out, b_out, c_out) = (
        dir.path().join("a"),
        dir.path().join("b"),
        dir.path().join("c"),
    );
    let mut a = args(&a_out);
    set(&mut a, "--steps", "2")?;
    run_ok(&a)?;
    let model = a_out.join("model.safetensors");
    for (out, init) in [(&b_out, true), (&c_out, false)] {
        let mut b = args(out);
        set(&mut b, "--steps", "1")?;
        set(&mut b, "--lr", "1e-12")?;
        set(&mut b, "--seed", "9")?;
        if init {
            b.extend(["--init".into(), model.display().to_string()]);
        }
        run_ok(&b)?;
    }
    let kept = max_diff(&model, &b_out.join("model.safetensors"))?;
    ensure!(kept < 1e-9, "--init moved the weights by {kept}");
    let seeded = max_diff(&model, &c_out.join("model.safetensors"))?;
    ensure!(seeded > 1e-3, "a seeded start equals the model ({seeded})");
    // The tiny model's weights do not fit the nviews config: refused, naming the file.
    let mut d = args(&dir.path().join("d"));
    d.extend(["--config", "nviews", "--init"].map(String::from));
    d.push(model.display().to_string());
    let o = Command::new(BIN).args(&d).output()?;
    let err = String::from_utf8_lossy(&o.stderr);
    ensure!(
        !o.status.success() && err.contains("model.safetensors"),
        "{err}"
    );
    ensure!(!dir.path().join("d/checkpoint.safetensors").exists());
    Ok(())
}
