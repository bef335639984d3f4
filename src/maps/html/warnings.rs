//! The page's warnings: what went wrong with the solve, in words, with what to do about it,
//! from `report.json`'s figures and what the folder holds.

use serde_json::Value;

use super::escape;
use super::full_maps::FullMaps;

/// One warning.
pub struct Warning {
    /// `error` (the page or the solve is incomplete), `warn` (the maps are suspect) or `info`.
    pub level: &'static str,
    pub text: String,
    pub todo: String,
}

fn warning(level: &'static str, text: String, todo: &str) -> Warning {
    Warning {
        level,
        text,
        todo: todo.into(),
    }
}

/// Share thresholds above which a class of failed pixels is worth a warning.
const SATURATED_SHARE: f64 = 0.005;
const DARK_SHARE: f64 = 0.02;
const DEGENERATE_SHARE: f64 = 0.005;
const NON_FINITE_SHARE: f64 = 0.0;
/// Share of solved pixels that failed the chi-square test, above which the model is suspect.
const ESCALATED_SHARE: f64 = 0.2;

fn count(report: &Value, group: &str, name: &str) -> f64 {
    report
        .get(group)
        .and_then(|g| g.get(name))
        .and_then(Value::as_f64)
        .unwrap_or(0.0)
}

fn percent(part: f64, whole: f64) -> String {
    format!("{:.2} %", 100.0 * part / whole.max(1.0))
}

fn from_report(r: &Value, out: &mut Vec<Warning>) {
    let total: f64 = r
        .get("pixels")
        .and_then(Value::as_object)
        .map_or(0.0, |m| m.values().filter_map(Value::as_f64).sum());
    let considered = total - count(r, "pixels", "outside_mask");
    let solved = count(r, "pixels", "solved");
    let classes: [(&str, f64, &'static str, &str); 4] = [
        (
            "saturated",
            SATURATED_SHARE,
            "warn",
            "lower the exposure (or the LED power) and capture again: clipped lights are dropped, \
             and with fewer than three left a pixel has no normal",
        ),
        (
            "dark",
            DARK_SHARE,
            "warn",
            "raise the exposure, check every LED fires (the frames below), or mask the background \
             (--background) if those pixels are not fabric",
        ),
        (
            "degenerate",
            DEGENERATE_SHARE,
            "warn",
            "the lights left at those pixels are nearly coplanar: usually shadows; capture with \
             more LEDs or check the rig's LED positions",
        ),
        (
            "non_finite",
            NON_FINITE_SHARE,
            "error",
            "the frames hold NaN or infinite values: re-decode them, or check the capture's files \
             against their hashes",
        ),
    ];
    for (name, limit, level, todo) in classes {
        let n = count(r, "pixels", name);
        if n > 0.0 && n / considered.max(1.0) > limit {
            out.push(warning(
                level,
                format!(
                    "{} pixels ({}) are {}",
                    n as u64,
                    percent(n, considered),
                    name.replace('_', " ")
                ),
                todo,
            ));
        }
    }
    let encoding = r
        .get("decode")
        .and_then(|d| d.get("encoding"))
        .and_then(Value::as_str);
    let benchmark = encoding.is_some_and(|e| e.starts_with("diligent"));
    let escalated = r.get("escalated").and_then(Value::as_f64).unwrap_or(0.0);
    if solved > 0.0 && escalated / solved > ESCALATED_SHARE {
        out.push(warning(
            "warn",
            format!(
                "{} of the solved pixels failed the model test (chi-square against the noise model)",
                percent(escalated, solved)
            ),
            if benchmark {
                "expected on a DiLiGenT-layout set: its images carry no sensor description, so \
                 the noise model is 16-bit quantisation only and real photographs fail it; judge \
                 the normals by the ground-truth figures below"
            } else {
                "the material is not Lambertian there (sheen, gloss, translucency) or the noise \
                 model or calibration is off: check the fit map, try --estimator adaptive, \
                 recalibrate if the failures follow the rig rather than the fabric"
            },
        ));
    }
    if solved == 0.0 && total > 0.0 {
        out.push(warning(
            "error",
            "no pixel was solved".into(),
            "check the frames (below) and the exposure; see the status map for why",
        ));
    }
    if let Some(cited) = r.get("calibration_cited_by_set").filter(|v| !v.is_null()) {
        let id = |v: &Value| {
            v.get("id")
                .and_then(Value::as_str)
                .unwrap_or("?")
                .to_string()
        };
        let used = r.get("calibration").filter(|v| !v.is_null());
        out.push(warning(
            "warn",
            format!(
                "calibration mismatch: the capture set cites bundle {} but the solve used {}",
                id(cited),
                used.map_or("none".to_string(), id)
            ),
            "solve again with the bundle the set cites (the default), or recapture with the \
             current calibration; the maps' light directions and gains may be off",
        ));
    }
    if encoding.is_some() && !benchmark && r.get("calibration").map_or(true, Value::is_null) {
        out.push(warning(
            "info",
            "solved without a calibration bundle: hand-measured LED positions, uniform gains".into(),
            "run psscan calibrate and capture with the bundle for measured lights and flat-field gains",
        ));
    }
    if r.get("sheen_everywhere").and_then(Value::as_bool) == Some(true) {
        out.push(warning(
            "info",
            "the adaptive estimator found sheen and fitted the sheen model everywhere".into(),
            "expected for velvet and satin; relight with the cloth BRDF below",
        ));
    }
}

/// Every warning the page shows, most serious first.
pub fn collect(report: std::result::Result<&Value, &str>, maps: &FullMaps) -> Vec<Warning> {
    let mut out = Vec::new();
    match report {
        Ok(r) => from_report(r, &mut out),
        Err(e) => out.push(warning(
            "error",
            e.to_string(),
            "solve again (--force) to rewrite it; the maps below are shown without the solve's \
             figures",
        )),
    }
    for m in &maps.missing {
        out.push(warning(
            "error",
            m.clone(),
            "the solve folder is incomplete: solve again, or restore the file",
        ));
    }
    let rank = |l: &str| match l {
        "error" => 0,
        "warn" => 1,
        _ => 2,
    };
    out.sort_by_key(|w| rank(w.level));
    out
}

/// The warnings as an HTML list (a line saying so when there are none).
pub fn render(warnings: &[Warning]) -> String {
    if warnings.is_empty() {
        return "<ul class=\"warnings\"><li class=\"ok\">no warnings: every check passed</li></ul>"
            .into();
    }
    let items: String = warnings
        .iter()
        .map(|w| {
            format!(
                "<li class=\"{}\"><b>{}</b>: {}<br><span class=\"todo\">what to do: {}</span></li>",
                w.level,
                w.level,
                escape(&w.text),
                escape(&w.todo)
            )
        })
        .collect();
    format!("<ul class=\"warnings\">{items}</ul>")
}
