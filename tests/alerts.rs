//! The alert rules that ship (docs/mbgate-alerts.yml, docs/watching.md "Alerts"),
//! held by Prometheus' own tools: `promtool check` takes the rules and the scrape
//! config that loads them, `promtool test rules` makes each alert fire and resolve
//! (tests/prometheus/mbgate-alerts.test.yml), and each alert's `runbook` is a section
//! of docs/troubleshooting.md. Skips, naming the Debian package, without promtool.

mod common;

use common::{peer, repo};
use std::process::Command;

/// `promtool ARGS` in the repository: its exit code and what it said.
fn promtool(args: &[&str]) -> (i32, String) {
    let out = Command::new("promtool")
        .args(args)
        .current_dir(repo())
        .output()
        .expect("run promtool");
    let said =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    eprintln!("$ promtool {}\n{said}", args.join(" "));
    (out.status.code().unwrap_or(-1), said)
}

/// The alert names in the rules file, in its order.
fn alert_names() -> Vec<String> {
    let rules = std::fs::read_to_string(repo().join("docs/mbgate-alerts.yml")).unwrap();
    rules
        .lines()
        .filter_map(|l| l.trim().strip_prefix("- alert: "))
        .map(str::to_owned)
        .collect()
}

#[test]
fn promtool_checks_the_rules_and_the_scrape_config_that_loads_them() {
    if !peer("promtool", "prometheus") {
        return;
    }
    let n = alert_names().len();
    let (code, said) = promtool(&["check", "rules", "docs/mbgate-alerts.yml"]);
    assert_eq!(code, 0, "{said}");
    assert!(
        said.contains(&format!("SUCCESS: {n} rules found")),
        "{said}"
    );
    let (code, said) = promtool(&["check", "config", "docs/prometheus.yml"]);
    assert_eq!(code, 0, "{said}");
    assert!(said.contains("SUCCESS: 1 rule files found"), "{said}");
}

#[test]
fn promtool_makes_every_alert_fire_and_resolve() {
    if !peer("promtool", "prometheus") {
        return;
    }
    let tests = "tests/prometheus/mbgate-alerts.test.yml";
    let (code, said) = promtool(&["test", "rules", tests]);
    assert_eq!(code, 0, "{said}");
    assert!(said.contains("SUCCESS"), "{said}");
    // Every alert has a case that expects it firing, and one after that expects it
    // gone.
    let text = std::fs::read_to_string(repo().join(tests)).unwrap();
    for name in alert_names() {
        let cases: Vec<&str> = text
            .split("- eval_time:")
            .filter(|c| c.contains(&format!("alertname: {name}\n")))
            .collect();
        let firing = cases.iter().position(|c| c.contains("exp_labels:"));
        let gone_after =
            firing.and_then(|i| cases[i..].iter().position(|c| c.contains("exp_alerts: []")));
        assert!(
            firing.is_some() && gone_after.is_some(),
            "{tests} makes {name} fire and then resolve"
        );
    }
}

/// A mistake in the test file (an alert expected that the rules do not make) fails
/// `promtool test rules`: the test above can fail.
#[test]
fn promtool_fails_an_alert_expected_that_does_not_fire() {
    if !peer("promtool", "prometheus") {
        return;
    }
    let dir = common::tempdir();
    let text = std::fs::read_to_string(repo().join("tests/prometheus/mbgate-alerts.test.yml"))
        .unwrap()
        .replace(
            "../../docs/mbgate-alerts.yml",
            repo().join("docs/mbgate-alerts.yml").to_str().unwrap(),
        )
        // The port stays closed: the alert still fires at 5 minutes, where the file
        // expects none.
        .replacen("values: '1 0 0 0 1 1'", "values: '1 0 0 0 0 0'", 1);
    let wrong = dir.path().join("wrong.test.yml");
    std::fs::write(&wrong, text).unwrap();
    let (code, said) = promtool(&["test", "rules", wrong.to_str().unwrap()]);
    assert_eq!(code, 1, "{said}");
    assert!(
        said.contains("alertname: MbgatePortClosed, time: 5m"),
        "{said}"
    );
}

/// Each alert says where to look first: a section of docs/troubleshooting.md named
/// after it.
#[test]
fn every_alert_names_its_section_of_the_troubleshooting_page() {
    let rules = std::fs::read_to_string(repo().join("docs/mbgate-alerts.yml")).unwrap();
    let page = std::fs::read_to_string(repo().join("docs/troubleshooting.md")).unwrap();
    let names = alert_names();
    assert!(names.len() >= 11, "{names:?}");
    for name in &names {
        let anchor = name.to_lowercase();
        assert!(
            rules.contains(&format!("runbook: \"docs/troubleshooting.md#{anchor}\"")),
            "{name}'s runbook"
        );
        assert!(
            page.contains(&format!("\n### {name}\n")),
            "docs/troubleshooting.md has a section {name}"
        );
    }
}

/// The fleet's scrape configs in docs/watching.md "Running a fleet" (file_sd, DNS)
/// are ones Prometheus takes, with the rules they load.
#[test]
fn the_fleet_scrape_configs_of_the_docs_pass_promtool() {
    if !peer("promtool", "prometheus") {
        return;
    }
    let page = std::fs::read_to_string(repo().join("docs/watching.md")).unwrap();
    let yaml: Vec<&str> = page
        .split("```yaml\n")
        .skip(1)
        .map(|b| b.split("```").next().unwrap())
        .collect();
    let file_sd = yaml
        .iter()
        .find(|b| b.starts_with("# /etc/prometheus/prometheus.yml"))
        .expect("the file_sd config");
    let dns = yaml
        .iter()
        .find(|b| b.contains("dns_sd_configs"))
        .expect("the DNS config");
    let rules = repo().join("docs/mbgate-alerts.yml");
    let dir = common::tempdir();
    for (name, text) in [
        (
            "file_sd.yml",
            file_sd.replace("/etc/prometheus/mbgate-alerts.yml", rules.to_str().unwrap()),
        ),
        ("dns.yml", format!("scrape_configs:\n{dns}")),
    ] {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        let (code, said) = promtool(&["check", "config", path.to_str().unwrap()]);
        assert_eq!(code, 0, "{name}: {said}");
    }
}
