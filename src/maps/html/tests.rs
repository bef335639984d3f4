use super::*;

#[test]
fn fill_replaces_known_keys_once_and_keeps_unknown_braces() {
    let out = fill("a{{X}}b{{Y}}c{{Z}}", &[("X", "{{Y}}"), ("Y", "2")]);
    assert_eq!(out, "a{{Y}}b2c{{Z}}");
}

#[test]
fn a_damaged_report_and_missing_maps_are_named_on_the_page() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join(REPORT_FILE), "{\"rig\": \"x\",").unwrap();
    let (html, summary) = build_page(dir.path());
    let err = summary.report_error.unwrap();
    assert!(err.contains("damaged"), "{err}");
    assert!(html.contains("report.json") && html.contains("damaged"));
    assert!(html.contains("albedo.png") && html.contains("missing"));
    assert!(html.contains("confidence.exr is missing"));
}
