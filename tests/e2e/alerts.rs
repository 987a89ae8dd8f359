//! The alert rules that ship (docs/mbgate-alerts.yml, docs/watching.md "Alerts"),
//! held by Prometheus' own tools: `promtool check` takes the rules and the scrape
//! config that loads them, `promtool test rules` makes each alert fire and resolve
//! (tests/prometheus/mbgate-alerts.test.yml), and each alert's `runbook` is a section
//! of docs/troubleshooting.md. Skips, naming the Debian package, without promtool.

use crate::common;

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

// ---------------------------------------------------------------------------------
// Live: a real Prometheus over two gateways (MBGATE_LONG=1)

/// One gateway of the fleet: a socat pty pair, a pymodbus RTU device (unit 1) on its
/// far end, the gateway on the near end with fixed Modbus and metrics ports (a
/// restart keeps them: Prometheus' target stays), and a pymodbus master polling it.
struct Cabinet {
    dir: tempfile::TempDir,
    socat: common::Socat,
    device: Option<common::Py>,
    gw: Option<common::Gateway>,
    _master: common::Py,
    metrics: String,
    /// Its web configuration file (`metrics.web_config`), if any.
    web: Option<std::path::PathBuf>,
}

impl Cabinet {
    fn start(web: Option<std::path::PathBuf>) -> Cabinet {
        let dir = common::tempdir();
        let socat = common::Socat::start(dir.path());
        let (listen, metrics) = (common::free_port(), common::free_port());
        let metrics = format!("127.0.0.1:{metrics}");
        let mut c = Cabinet {
            device: None,
            gw: None,
            _master: common::Py::start(
                "poller.py",
                &[
                    "--port",
                    &listen.to_string(),
                    "--unit",
                    "1",
                    "--every",
                    "0.2",
                ],
            ),
            metrics,
            socat,
            dir,
            web,
        };
        std::fs::write(c.dir.path().join("listen"), listen.to_string()).unwrap();
        c.start_device();
        c.start_gateway();
        c
    }

    fn start_device(&mut self) {
        let dev = self.socat.dev.to_str().unwrap().to_owned();
        let args = [
            "--port", &dev, "--framer", "rtu", "--baud", "19200", "--units", "1",
        ];
        self.device = Some(common::Py::start("serial_device.py", &args));
    }

    /// The gateway: RTU on the pty, short timeouts and back-off so that a unit's
    /// death and return show within seconds (the rules' `for:` is shortened too).
    fn start_gateway(&mut self) {
        let listen = std::fs::read_to_string(self.dir.path().join("listen")).unwrap();
        let web = self.web.as_ref().map_or_else(String::new, |w| {
            format!("web_config = {:?}", w.display().to_string())
        });
        let text = common::Cfg::new(&self.socat.gw)
            .pty_line()
            .serial("framing = \"rtu\"")
            .serial("flow_control = \"none\"")
            .relay("response_timeout_ms = 300")
            .relay("unit_backoff_ms = 300")
            .relay("unit_backoff_max_ms = 600")
            .log_level("info")
            .metrics(&format!("listen = \"{}\"", self.metrics))
            .metrics(&web)
            .render()
            .replace(
                "listen = \"127.0.0.1:0\"",
                &format!("listen = \"127.0.0.1:{listen}\""),
            );
        let dir = self.dir.path().join("gateway");
        std::fs::create_dir_all(&dir).unwrap();
        let gw = common::Gateway::launch_text(&text, &dir, common::Launch::default());
        gw.proc.metrics_addr(std::time::Duration::from_secs(10));
        self.gw = Some(gw);
    }

    fn line(&self) -> String {
        self.socat.gw.display().to_string()
    }

    fn log(&self) -> String {
        self.gw.as_ref().map(|g| g.log()).unwrap_or_default()
    }
}

/// A Prometheus from the Debian package, with the shipped scrape config and rules
/// made quick by an overlay, scraping `targets` (address, site, bus).
struct Prometheus {
    child: std::process::Child,
    addr: String,
    _dir: tempfile::TempDir,
}

/// Two gateways behind TLS and a password, as docs/watching.md "Behind TLS and a
/// password" makes them: a CA and the gateways' certificate (openssl), a client
/// certificate for Prometheus, a user whose hash `mbgate hash-password` made, and two
/// web configuration files: A's asks for a client certificate, B's does not.
struct Behind {
    dir: tempfile::TempDir,
    pki: common::pki::Pki,
}

impl Behind {
    fn new() -> Behind {
        let dir = common::tempdir();
        let pki = common::pki::Pki::new(&dir.path().join("pki"));
        pki.master("prometheus", "ca", None, 30);
        let mut child = Command::new(env!("CARGO_BIN_EXE_mbgate"))
            .args(["hash-password", "--user", "prometheus"])
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        use std::io::Write;
        writeln!(child.stdin.take().unwrap(), "scrape it").unwrap();
        let user = String::from_utf8(child.wait_with_output().unwrap().stdout).unwrap();
        let tls = format!(
            "tls_server_config:\n  cert_file: {}\n  key_file: {}\n",
            pki.pem("gateway"),
            pki.key("gateway")
        );
        let required = format!(
            "  client_auth_type: RequireAndVerifyClientCert\n  client_ca_file: {}\n",
            pki.pem("ca")
        );
        let a = format!("{tls}{required}basic_auth_users:\n  {user}");
        let b = format!("{tls}basic_auth_users:\n  {user}");
        std::fs::write(dir.path().join("web-a.yml"), a).unwrap();
        std::fs::write(dir.path().join("web-b.yml"), b).unwrap();
        std::fs::write(dir.path().join("password"), "scrape it\n").unwrap();
        std::fs::write(dir.path().join("wrong"), "scrape it not\n").unwrap();
        Behind { dir, pki }
    }

    fn web(&self, which: &str) -> std::path::PathBuf {
        self.dir.path().join(format!("web-{which}.yml"))
    }

    /// The shipped scrape config's lines for https, uncommented and given this
    /// folder's files: the password file `password`.
    fn lines(&self, head: &str, password: &str) -> String {
        let mut out = String::new();
        let mut on = false;
        for line in head.lines() {
            on = on || line.trim() == "# scheme: https";
            let line = match line.strip_prefix("    # ") {
                Some(rest) if on => format!("    {rest}"),
                _ => line.to_owned(),
            };
            let line = line
                .replace("/etc/prometheus/mbgate-ca.pem", &self.pki.pem("ca"))
                .replace(
                    "/etc/prometheus/mbgate-client.pem",
                    &self.pki.pem("prometheus"),
                )
                .replace(
                    "/etc/prometheus/mbgate-client.key",
                    &self.pki.key("prometheus"),
                )
                .replace(
                    "/etc/prometheus/mbgate.password",
                    &self.dir.path().join(password).display().to_string(),
                );
            out += &line;
            out.push('\n');
        }
        out
    }
}

impl Prometheus {
    /// A Prometheus from the Debian package scraping `targets` (address, site,
    /// bus), the gateways behind `behind`'s TLS and user (the
    /// shipped config's lines for it uncommented), and a job `wrong-password` that
    /// scrapes the first gateway with a wrong password.
    fn start(targets: &[(&str, &str, &str)], behind: Option<&Behind>) -> Prometheus {
        let dir = common::tempdir();
        // The shipped scrape config, its targets ours, scraped and evaluated every
        // second.
        let shipped = std::fs::read_to_string(repo().join("docs/prometheus.yml")).unwrap();
        let (head, tail) = shipped
            .split_once("    static_configs:\n")
            .expect("docs/prometheus.yml has static_configs");
        let tail = &tail[tail
            .find("    # Many gateways")
            .expect("the file_sd comment")..];
        let mut statics = String::from("    static_configs:\n");
        for (addr, site, bus) in targets {
            statics += &format!(
                "      - targets: [\"{addr}\"]\n        labels: {{site: {site}, bus: {bus}}}\n"
            );
        }
        assert!(head.contains("scrape_interval: 15s"), "{head}");
        let quick = |head: &str| {
            head.replace(
                "scrape_interval: 15s",
                "scrape_interval: 1s\n    scrape_timeout: 1s",
            )
        };
        let shipped = head;
        let head = match behind {
            Some(b) => b.lines(shipped, "password"),
            None => shipped.to_owned(),
        };
        let mut config =
            "global:\n  evaluation_interval: 1s\n".to_owned() + &quick(&head) + &statics + tail;
        if let Some(b) = behind {
            // The same job with the wrong password, on the first gateway: a job the
            // rules do not watch (its name does not start with mbgate).
            let job = &shipped[shipped.find("  - job_name: mbgate").unwrap()..];
            let job = b.lines(job, "wrong");
            config += &quick(&job).replace("job_name: mbgate", "job_name: wrong-password");
            config += &format!(
                "    static_configs:\n      - targets: [\"{}\"]\n",
                targets[0].0
            );
        }
        std::fs::write(dir.path().join("prometheus.yml"), config).unwrap();
        std::fs::write(dir.path().join("mbgate-alerts.yml"), quick_rules()).unwrap();
        let addr = format!("127.0.0.1:{}", common::free_port());
        let child = Command::new("prometheus")
            .arg(format!(
                "--config.file={}",
                dir.path().join("prometheus.yml").display()
            ))
            .arg(format!(
                "--storage.tsdb.path={}",
                dir.path().join("data").display()
            ))
            .arg(format!("--web.listen-address={addr}"))
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .stderr(std::fs::File::create(dir.path().join("prometheus.log")).unwrap())
            .spawn()
            .expect("run prometheus");
        let p = Prometheus {
            child,
            addr,
            _dir: dir,
        };
        common::wait_for(
            "Prometheus ready",
            std::time::Duration::from_secs(60),
            || p.get("/-/ready").is_some_and(|b| b.contains("Ready")),
        );
        p
    }

    /// The body of `path`, if Prometheus answered.
    fn get(&self, path: &str) -> Option<String> {
        use std::io::{Read, Write};
        let mut s = std::net::TcpStream::connect(&self.addr).ok()?;
        s.set_read_timeout(Some(std::time::Duration::from_secs(10)))
            .ok()?;
        // HTTP/1.0: the whole body, never chunked.
        write!(s, "GET {path} HTTP/1.0\r\nHost: {}\r\n\r\n", self.addr).ok()?;
        let mut all = String::new();
        s.read_to_string(&mut all).ok()?;
        all.split_once("\r\n\r\n").map(|(_, b)| b.to_owned())
    }

    /// Every alert pending or firing now: (state, labels).
    fn alerts(&self) -> Vec<(String, std::collections::BTreeMap<String, String>)> {
        let body = self.get("/api/v1/alerts").expect("Prometheus answers");
        let v: serde_json::Value = serde_json::from_str(&body).expect("JSON");
        let alerts = v["data"]["alerts"].as_array().expect("alerts").clone();
        alerts
            .iter()
            .map(|a| {
                let labels = a["labels"].as_object().unwrap();
                let labels = labels
                    .iter()
                    .map(|(k, v)| (k.clone(), v.as_str().unwrap().to_owned()))
                    .collect();
                (a["state"].as_str().unwrap().to_owned(), labels)
            })
            .collect()
    }

    /// When the rules were last evaluated, as Prometheus says it.
    fn last_evaluation(&self) -> String {
        let body = self.get("/api/v1/rules").unwrap_or_default();
        let v: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
        v["data"]["groups"][0]["lastEvaluation"]
            .as_str()
            .unwrap_or_default()
            .to_owned()
    }

    /// Whether every target is up now.
    fn all_up(&self, n: usize) -> bool {
        let query = url_encoded("up{job=~\"mbgate.*\"}");
        let Some(body) = self.get(&format!("/api/v1/query?query={query}")) else {
            return false;
        };
        let v: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
        let up = v["data"]["result"].as_array().cloned().unwrap_or_default();
        up.len() == n && up.iter().all(|s| s["value"][1] == "1")
    }
}

impl Drop for Prometheus {
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        for _ in 0..100 {
            if self.child.try_wait().ok().flatten().is_some() {
                return;
            }
            std::thread::sleep(std::time::Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// docs/mbgate-alerts.yml made quick for a test that lasts a minute: each `for:` of
/// N minutes becomes 3N seconds, each 5-minute window 15 seconds (Prometheus scrapes
/// and evaluates every second here).
fn quick_rules() -> String {
    let rules = std::fs::read_to_string(repo().join("docs/mbgate-alerts.yml")).unwrap();
    let mut out = String::new();
    for line in rules.lines() {
        let line = match line.trim_start().strip_prefix("for: ") {
            Some(m) => {
                let minutes: u32 = m.trim_end_matches('m').parse().expect("for: Nm");
                format!(
                    "{}for: {}s",
                    &line[..line.len() - line.trim_start().len()],
                    3 * minutes
                )
            }
            None => line.replace("[5m]", "[15s]"),
        };
        out += &line;
        out.push('\n');
    }
    assert!(!out.contains("[5m]") && out.contains("for: 3s"), "{out}");
    out
}

/// An alert as the test names it: its name, instance, and the line and unit it is
/// about ("" where it has none).
type Named = (String, String, String, String);

fn named(labels: &std::collections::BTreeMap<String, String>) -> Named {
    let get = |k: &str| labels.get(k).cloned().unwrap_or_default();
    (get("alertname"), get("instance"), get("line"), get("unit"))
}

/// Waits (bounded) until the alerts pending or firing are exactly `want`, all
/// firing, each with the site and bus of its gateway; fails with what was seen.
fn wait_for_alerts(
    prom: &Prometheus,
    want: &[Named],
    sites: &[(&str, &str, &str)],
    what: &str,
    logs: &dyn Fn() -> String,
) {
    let want: std::collections::BTreeSet<Named> = want.iter().cloned().collect();
    let start = std::time::Instant::now();
    let mut seen = Vec::new();
    while start.elapsed() < std::time::Duration::from_secs(90) {
        seen = prom.alerts();
        let got: std::collections::BTreeSet<Named> = seen.iter().map(|(_, l)| named(l)).collect();
        if got == want && seen.iter().all(|(state, _)| state == "firing") {
            for (_, labels) in &seen {
                let (_, site, bus) = sites
                    .iter()
                    .find(|(addr, ..)| labels["instance"] == *addr)
                    .expect("a gateway's alert");
                assert_eq!(labels["site"], *site, "{labels:?}");
                assert_eq!(labels["bus"], *bus, "{labels:?}");
                assert!(labels.contains_key("severity"), "{labels:?}");
            }
            eprintln!("{what}: {want:?}");
            return;
        }
        std::thread::sleep(std::time::Duration::from_millis(250));
    }
    panic!(
        "{what}: want exactly {want:?} firing, saw {seen:#?}\n{}",
        logs()
    );
}

/// The whole chain, live: two gateways, each with a pymodbus device on a socat pty
/// and a pymodbus master polling it, each behind TLS and a password (A asking for a
/// client certificate too), scraped over https by a real Prometheus with the shipped
/// config (its lines for https uncommented) and rules (quickened), and by a job with a
/// wrong password, which is down and says why; one device killed, then one gateway's port, then a
/// whole gateway: Prometheus' API says exactly the expected alert fires, for the
/// right gateway, line and unit, and that it resolves once the fault is undone.
/// About two minutes: MBGATE_LONG=1.
#[test]
fn live_prometheus_fires_exactly_the_expected_alerts_and_resolves_them() {
    if std::env::var_os("MBGATE_LONG").is_none() {
        eprintln!("skipped: live Prometheus test (about 2 minutes): MBGATE_LONG=1 runs it");
        return;
    }
    if !peer("prometheus", "prometheus") || !peer("socat", "socat") {
        return;
    }
    // Both gateways behind TLS and a password, A asking for a client certificate too.
    let behind = Behind::new();
    let mut a = Cabinet::start(Some(behind.web("a")));
    let mut b = Cabinet::start(Some(behind.web("b")));
    let (ia, ib) = (a.metrics.clone(), b.metrics.clone());
    let sites = [
        (ia.as_str(), "plant-a", "hall-1"),
        (ib.as_str(), "plant-a", "hall-2"),
    ];
    let prom = Prometheus::start(&sites, Some(&behind));
    let logs =
        |a: &Cabinet, b: &Cabinet| format!("gateway A:\n{}\ngateway B:\n{}", a.log(), b.log());
    common::wait_for(
        "both targets up",
        std::time::Duration::from_secs(60),
        || prom.all_up(2),
    );
    let alert = |name: &str, instance: &str, line: &str, unit: &str| -> Named {
        (name.into(), instance.into(), line.into(), unit.into())
    };

    // All well: nothing pending or firing, once the rules have been evaluated over
    // both gateways' series.
    let before = prom.last_evaluation();
    common::wait_for(
        "an evaluation of the rules",
        std::time::Duration::from_secs(30),
        || prom.last_evaluation() != before,
    );
    wait_for_alerts(&prom, &[], &sites, "all well", &|| logs(&a, &b));

    dashboard_queries_answer(&prom, &ia);
    wrong_password_is_down_and_says_why(&prom, &ia);
    assert!(
        a.log()
            .contains("login from 127.0.0.1 refused: wrong user or password"),
        "{}",
        a.log()
    );

    // Gateway A's device dies: its unit 1 is not answering, and nothing else.
    a.device = None;
    let want = [alert("MbgateUnitNotAnswering", &ia, &a.line(), "1")];
    wait_for_alerts(&prom, &want, &sites, "A's device dead", &|| logs(&a, &b));
    a.start_device();
    wait_for_alerts(&prom, &[], &sites, "A's device back", &|| logs(&a, &b));

    // Gateway B's port goes (the cable pulled: socat gone, the pty with it).
    b.device = None;
    b.socat.stop();
    let want = [alert("MbgatePortClosed", &ib, &b.line(), "")];
    wait_for_alerts(&prom, &want, &sites, "B's port gone", &|| logs(&a, &b));
    b.socat.restart();
    b.start_device();
    wait_for_alerts(&prom, &[], &sites, "B's port back", &|| logs(&a, &b));

    // Gateway A is gone as a whole: only MbgateDown, its other series stale.
    let mut gw = a.gw.take().unwrap();
    gw.proc.signal("KILL");
    drop(gw);
    let want = [alert("MbgateDown", &ia, "", "")];
    wait_for_alerts(&prom, &want, &sites, "A down", &|| logs(&a, &b));
    a.start_gateway();
    wait_for_alerts(&prom, &[], &sites, "A back", &|| logs(&a, &b));
}

/// The job with the wrong password: its target is down, and Prometheus' scrape error
/// says the gateway answered 401 (or 429, the source past its budget of checks).
fn wrong_password_is_down_and_says_why(prom: &Prometheus, instance: &str) {
    let start = std::time::Instant::now();
    let down = || -> (bool, String) {
        let body = prom.get("/api/v1/targets").unwrap_or_default();
        let v: serde_json::Value = serde_json::from_str(&body).unwrap_or_default();
        let targets = v["data"]["activeTargets"]
            .as_array()
            .cloned()
            .unwrap_or_default();
        let wrong = targets
            .iter()
            .find(|t| t["labels"]["job"] == "wrong-password");
        let said = format!("{wrong:?}");
        let down = wrong.is_some_and(|t| {
            t["health"] == "down"
                && t["labels"]["instance"] == instance
                && t["lastError"].as_str().is_some_and(|e| {
                    // 401; or, scraped every second here, past the source's five
                    // checks and one every 5 s, 429 (every 15 s it stays 401).
                    e.contains("server returned HTTP status 401 Unauthorized")
                        || e.contains("server returned HTTP status 429 Too Many Requests")
                })
        });
        (down, said)
    };
    loop {
        let (down, said) = down();
        if down {
            eprintln!("wrong password: {said}");
            break;
        }
        assert!(
            start.elapsed() < std::time::Duration::from_secs(30),
            "the wrong password's target down, with its error: {said}"
        );
        std::thread::sleep(std::time::Duration::from_millis(250));
    }
    let query = url_encoded("up{job=\"wrong-password\"}");
    let body = prom.get(&format!("/api/v1/query?query={query}")).unwrap();
    assert!(body.contains("\"0\"]"), "{body}");
}

/// Every query of the Grafana dashboard (docs/grafana-dashboard.json), its variables
/// set to this fleet and gateway `instance`, is one Prometheus takes, and each has
/// series while all is well, but those that show only trouble, or learned timeouts
/// (these gateways' are fixed).
fn dashboard_queries_answer(prom: &Prometheus, instance: &str) {
    let text = std::fs::read_to_string(repo().join("docs/grafana-dashboard.json")).unwrap();
    let dashboard: serde_json::Value = serde_json::from_str(&text).unwrap();
    let may_be_empty = [
        "Units not answering, by gateway",
        "Gateways down, lines not open",
        "Learned timeouts, per unit",
        "Units not answering",
    ];
    let mut asked = 0;
    for panel in dashboard["panels"].as_array().unwrap() {
        let title = panel["title"].as_str().unwrap();
        for target in panel["targets"].as_array().into_iter().flatten() {
            let expr = target["expr"].as_str().unwrap();
            let query = expr
                .replace("$job", "mbgate.*")
                .replace("$site", ".*")
                .replace("$instance", instance)
                .replace("$line", ".*")
                .replace("$__rate_interval", "15s");
            // A rate needs two scrapes of a series: asked again (bounded) until it
            // has them.
            let start = std::time::Instant::now();
            loop {
                let body = prom
                    .get(&format!("/api/v1/query?query={}", url_encoded(&query)))
                    .expect("Prometheus answers");
                let v: serde_json::Value = serde_json::from_str(&body).expect("JSON");
                assert_eq!(v["status"], "success", "{title}: {query}: {body}");
                let empty = v["data"]["result"].as_array().is_none_or(|r| r.is_empty());
                if !empty || may_be_empty.contains(&title) {
                    break;
                }
                assert!(
                    start.elapsed() < std::time::Duration::from_secs(30),
                    "{title}: {query} has no series: {body}"
                );
                std::thread::sleep(std::time::Duration::from_millis(250));
            }
            asked += 1;
        }
    }
    assert!(asked > 30, "{asked} queries");
}

/// `s` as a URL's query value.
fn url_encoded(s: &str) -> String {
    s.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}
