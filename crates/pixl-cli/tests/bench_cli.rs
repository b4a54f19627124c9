//! `pixl bench parity` and `pixl bench train-step` through the real binary, on the CPU (the dry
//! run of `scripts/gpu-check.sh`): the same computation on both sides agrees exactly, bf16 differs
//! from f32 by a small but non-zero amount, a tolerance below that error fails the command, and a
//! training step reports a finite loss that matches an L1 loss of the freshly initialised network
//! (which returns its source) computed here.
mod common;
use common::pixl_q;

const PARITY: [&str; 9] = [
    "bench", "parity", "--device", "cpu", "--config", "tiny", "--size", "48x32", "--json",
];

#[test]
fn parity_on_the_cpu_is_exact_and_bf16_is_near() {
    let v = pixl_q(&PARITY).ok().json();
    assert_eq!(v["failed"], 0);
    let rows = v["rows"].as_array().unwrap();
    assert_eq!(
        rows.len(),
        3,
        "f32, bf16, bf16 vs f32 (no --fixtures: no estimator rows)"
    );
    for r in &rows[..2] {
        assert_eq!(
            r["rel_l2"], 0.0,
            "the same dtype on the same device is bitwise the same: {r}"
        );
        assert_eq!(r["pass"], true);
    }
    let bf16 = rows[2]["rel_l2"].as_f64().unwrap();
    // bf16 keeps 8 bits of mantissa (relative rounding 2^-9 ≈ 2e-3 per value): the change the
    // network makes is off by a fraction of a per cent to a few per cent, never by nothing.
    assert!(bf16 > 1e-4 && bf16 < 0.1, "bf16 vs f32 relative error {bf16}");
}

#[test]
fn parity_fails_over_its_tolerance() {
    let mut args = PARITY.to_vec();
    args.extend(["--tol-bf16-vs-f32", "1e-9"]);
    let o = pixl_q(&args);
    assert!(!o.success(), "a 1e-9 tolerance on bf16 must fail");
    assert!(o.stderr.contains("1 of 3 parity checks over tolerance"), "{}", o.stderr);
    let v = o.json();
    assert_eq!(v["failed"], 1);
    assert_eq!(v["rows"][2]["pass"], false);
}

#[test]
fn parity_names_a_wrong_fixtures_folder() {
    let dir = common::tempdir();
    let mut args = PARITY[..8].to_vec();
    args.extend(["--fixtures", common::s(dir.path())]);
    let o = pixl_q(&args);
    assert!(!o.success());
    assert!(
        o.stderr.contains("is not the repository's fixtures folder"),
        "{}",
        o.stderr
    );
}

#[test]
fn train_step_reports_the_l1_loss_of_a_fresh_network() {
    let v = pixl_q(&[
        "bench",
        "train-step",
        "--config",
        "tiny",
        "--size",
        "32x32",
        "--batch",
        "2",
        "--warmups",
        "0",
        "--runs",
        "1",
        "--json",
    ])
    .ok()
    .json();
    assert_eq!(v["batch"], 2);
    assert_eq!(v["timing"]["runs_ms"].as_array().unwrap().len(), 1);
    // The first step's loss is that of the initial network, which returns its source: the mean
    // |source − target| of two independent uniform [0, 1) images, whose expectation is 1/3
    // (6144 values: standard deviation of the mean ≈ 0.003).
    let loss = v["last_loss"].as_f64().unwrap();
    assert!((loss - 1.0 / 3.0).abs() < 0.02, "first-step loss {loss}");
}
