//! The status page (docs/watching.md) in a real browser: headless Chromium (Debian's
//! `chromium`, installed by scripts/test) loads it from the metrics listener while a
//! master polls; the request rate and the frame list appear, decoded, and update. At a
//! phone's width (420 px) and a desktop's (1280 px) nothing is wider than the window,
//! the chart's y axis is labelled in ms, and with a unit not answering the headline
//! says so. A screenshot at a phone's size goes to target/status-page.png. Without
//! chromium (scripts/test --no-install) the test skips, saying so (common::peer).

use crate::common;
use common::*;
use std::io::{Read, Write};
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread;
use std::time::Duration;

fn chromium() -> Option<&'static str> {
    ["chromium", "chromium-browser"].into_iter().find(|b| {
        Command::new(b)
            .arg("--version")
            .output()
            .is_ok_and(|o| o.status.success())
    })
}

/// Chromium, headless, at a phone's width, `extra` flags, on `url`: its stdout.
fn browse(browser: &str, url: &str, extra: &[&str]) -> String {
    browse_at(browser, 420, url, extra)
}

/// Chromium, headless, `width` pixels wide, `extra` flags, on `url`: its stdout. A
/// browser that hangs (seen once on a machine loaded ten times over its cores: a
/// screenshot that never came) is killed after a minute and started again, twice at
/// most, so the test fails with a message rather than never ending.
fn browse_at(browser: &str, width: u32, url: &str, extra: &[&str]) -> String {
    let mut tries = 0;
    loop {
        tries += 1;
        let out = Command::new("timeout")
            .args(["-k", "5", "60", browser])
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-dev-shm-usage",
                "--no-first-run",
                "--hide-scrollbars",
                &format!("--window-size={width},915"),
                "--virtual-time-budget=3000",
            ])
            .args(extra)
            .arg(url)
            .output()
            .expect("run chromium");
        // timeout(1): 124 when it stopped the browser, 137 when it had to kill it.
        let hung = matches!(out.status.code(), Some(124 | 137));
        if hung && tries < 3 {
            eprintln!("chromium hung for a minute: started again");
            continue;
        }
        assert!(
            out.status.success(),
            "chromium failed ({:?}, try {tries}): {}",
            out.status.code(),
            String::from_utf8_lossy(&out.stderr)
        );
        return String::from_utf8_lossy(&out.stdout).into_owned();
    }
}

/// The text right after `marker`, up to the next `<` or `)`.
fn text_after<'a>(dom: &'a str, marker: &str) -> &'a str {
    let at = dom
        .find(marker)
        .unwrap_or_else(|| panic!("{marker} not in:\n{dom}"));
    let rest = &dom[at + marker.len()..];
    &rest[..rest.find(['<', ')']).unwrap()]
}

#[test]
fn the_status_page_shows_live_rates_and_decoded_frames_in_a_browser() {
    let Some(browser) = chromium() else {
        assert!(
            !peer("chromium", "chromium"),
            "chromium is installed, but `chromium --version` fails"
        );
        return;
    };
    let dir = tempdir();
    let socat = Socat::start(dir.path());
    let _dev = RawDevice::start(&socat.dev, register_device(&[1], Duration::ZERO));
    // The device answers at once; a browser beside a busy machine can hold its answer
    // past the default second.
    let cfg = Cfg::new(&socat.gw)
        .pty_line()
        .serial("flow_control = \"none\"")
        .relay("response_timeout_ms = 5000")
        .metrics("listen = \"127.0.0.1:0\"");
    let mut gw = Gateway::start(&cfg, dir.path());
    // The log says where the page is.
    gw.wait_log("status page on http://", Duration::from_secs(5));
    let log = gw.log();
    let http = log.split("status page on http://").nth(1).unwrap();
    let url = format!("http://{}/", http.split('/').next().unwrap());
    // A master polls register 7 every 20 ms throughout.
    let stop = Arc::new(AtomicBool::new(false));
    let mut m = gw.connect();
    let polling = stop.clone();
    let master = thread::spawn(move || {
        let mut tid = 0u16;
        while !polling.load(Ordering::Relaxed) {
            assert_eq!(
                transact(&mut m, &read_req(tid, 1, 7, 3)),
                read_reply(tid, 1, &[7, 8, 9])
            );
            tid = tid.wrapping_add(1);
            thread::sleep(Duration::from_millis(20));
        }
    });

    // The page was open a moment ago (frames are recorded only while it is), and the
    // gateway samples a point a second: two make a rate.
    let host = url
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_owned();
    let mut s = std::net::TcpStream::connect(&host).unwrap();
    write!(s, "GET /status.json HTTP/1.1\r\n\r\n").unwrap();
    let mut json = String::new();
    s.read_to_string(&mut json).unwrap();
    assert!(
        json.contains("\"frames_total\":0"),
        "nothing recorded before: {json}"
    );
    thread::sleep(Duration::from_millis(2100));
    let mut s = std::net::TcpStream::connect(&host).unwrap();
    write!(s, "GET /status.json HTTP/1.1\r\n\r\n").unwrap();
    let mut json = String::new();
    s.read_to_string(&mut json).unwrap();
    let at = json.find("\"frames_total\":").expect("frames_total") + 15;
    let before: u64 = json[at..].split(',').next().unwrap().parse().unwrap();
    assert!(before > 0, "recorded while the page was open: {json}");
    let first = browse(browser, &url, &["--dump-dom"]);
    // Several polls of /status.json: the rate is a number above zero.
    let updates: u32 = text_after(&first, "(update ").parse().unwrap();
    assert!(updates >= 2, "{updates} updates");
    let rate: f64 = text_after(&first, "id=\"rate-0\"><b>").parse().unwrap();
    assert!(rate > 1.0, "req/s {rate}");
    assert!(first.contains("Line ") && first.contains(socat.gw.to_str().unwrap()));
    // The frames decoded: both directions, unit 1, FC 03, address 7, count 3, the hex.
    let rows = |dom: &str| -> Vec<String> {
        let table = &dom[dom.find("id=\"frames-0\"").expect("frame table")..];
        let body = &table[..table.find("</table>").unwrap()];
        body.split("<tr>").skip(2).map(str::to_owned).collect()
    };
    let frames = rows(&first);
    assert!(frames.len() >= 4, "{frames:?}");
    let out = frames
        .iter()
        .find(|r| r.contains("gw-&gt;serial"))
        .expect("a request");
    assert!(
        out.contains(
            "<td data-label=\"unit\">1</td><td data-label=\"FC\">0x03</td>\
             <td data-label=\"addr\">7</td><td data-label=\"count\">3</td>"
        ) && out.contains("00 00 00 06 01 03 00 07 00 03"),
        "{out}"
    );
    let back = frames
        .iter()
        .find(|r| r.contains("serial-&gt;gw"))
        .expect("a reply");
    assert!(
        back.contains("00 00 00 09 01 03 06 00 07 00 08 00 09"),
        "{back}"
    );
    assert!(first.contains("healthy"), "{first}");
    let total = |dom: &str| -> u64 { text_after(dom, "frames (of ").parse().unwrap() };

    // Newer than what there was before the browser came: the page shows the frames
    // recorded since, having polled several times.
    assert!(
        total(&first) > before,
        "{} frames, {before} before",
        total(&first)
    );
    // Nothing wider than the window, on a phone or a desktop: neither the page nor a
    // table in its own scrolling box (the page measures both after each update).
    for width in [420, 1280] {
        let dom = browse_at(browser, width, &url, &["--dump-dom"]);
        let body = &dom[dom.find("<body").expect("a body")..];
        let body = &body[..body.find('>').unwrap()];
        assert!(
            body.contains("data-overflow=\"0\"") && body.contains("data-inner-overflow=\"0\""),
            "at {width} px: {body}"
        );
        // A unit's state ("answering", "NOT ANSWERING") is never broken inside a word;
        // on a desktop the line's tiles take one row (the last one once stood alone).
        assert!(
            body.contains("data-broken-words=\"0\""),
            "at {width} px: {body}"
        );
        if width == 1280 {
            assert!(
                body.contains("data-tile-rows=\"1\""),
                "at {width} px: {body}"
            );
        }
        // The chart's y axis: three labels in ms, from the top down to 0 ms.
        let axis = &dom[dom.find("id=\"yaxis-0\"").expect("a y axis")..];
        let axis = &axis[..axis.find("</div>").unwrap()];
        assert_eq!(axis.matches(" ms</span>").count(), 3, "{axis}");
        assert!(axis.contains("<span>0 ms</span>"), "{axis}");
    }
    // A unit that never answers (no device has unit 9): after its third timeout the
    // headline says the gateway is not healthy, and why.
    let mut asker = gw.connect();
    for tid in 0..3 {
        let reply = transact(&mut asker, &read_req(tid, 9, 0, 1));
        assert_eq!(reply[7..], [0x83, 0x0B], "{}", hexs(&reply));
    }
    let dom = browse(browser, &url, &["--dump-dom"]);
    assert!(dom.contains("NOT HEALTHY"), "{dom}");
    let why = text_after(&dom, "<div id=\"why\" class=\"bad\">");
    assert!(
        why.starts_with(&format!(
            "unit 9 on {} not answering (3 timeouts, 0 replies",
            socat.gw.display()
        )),
        "{why}"
    );

    let shot = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("target/status-page.png");
    let _ = std::fs::remove_file(&shot);
    browse(
        browser,
        &url,
        &[&format!("--screenshot={}", shot.display())],
    );
    let png = std::fs::read(&shot).expect("the screenshot");
    assert!(
        png.starts_with(b"\x89PNG") && png.len() > 10_000,
        "{} bytes",
        png.len()
    );

    stop.store(true, Ordering::Relaxed);
    master.join().expect("the master was answered throughout");
    gw.stop();
}

/// The page behind TLS and a password (docs/watching.md "Behind TLS and a password"):
/// Chromium opens `https://user:password@host/` (the gateway's certificate trusted by
/// its public key's hash, as a CA installed in the browser would) and shows the line
/// and its frames, polling `/status.json` with the credentials it was given; without
/// them it gets 401, shows nothing of the plant, and the body's bytes say nothing but
/// that a user and password are needed.
#[test]
fn the_status_page_over_https_with_a_password_in_a_browser() {
    let Some(browser) = chromium() else {
        assert!(!peer("chromium", "chromium"));
        return;
    };
    if !peer("curl", "curl") || !peer("openssl", "openssl") {
        return;
    }
    let dir = tempdir();
    let pki = common::pki::Pki::new(&dir.path().join("pki"));
    let socat = Socat::start(dir.path());
    let _dev = RawDevice::start(&socat.dev, register_device(&[1], Duration::ZERO));
    let hash = {
        let mut child = Command::new(env!("CARGO_BIN_EXE_mbgate"))
            .args(["hash-password", "--cost", "4"])
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        writeln!(child.stdin.take().unwrap(), "look at the plant").unwrap();
        let out = child.wait_with_output().unwrap();
        String::from_utf8(out.stdout).unwrap().trim().to_owned()
    };
    let web = dir.path().join("web.yml");
    std::fs::write(
        &web,
        format!(
            "tls_server_config:\n  cert_file: {}\n  key_file: {}\nbasic_auth_users:\n  operator: {hash}\n",
            pki.pem("gateway"),
            pki.key("gateway")
        ),
    )
    .unwrap();
    let cfg = Cfg::new(&socat.gw)
        .pty_line()
        .serial("flow_control = \"none\"")
        .relay("response_timeout_ms = 5000")
        .metrics("listen = \"127.0.0.1:0\"")
        .metrics(&format!("web_config = {:?}", web.display().to_string()));
    let mut gw = Gateway::start(&cfg, dir.path());
    let port = gw.proc.metrics_addr(Duration::from_secs(10)).port();
    let line = socat.gw.display().to_string();
    let stop = Arc::new(AtomicBool::new(false));
    let mut m = gw.connect();
    let polling = stop.clone();
    let master = thread::spawn(move || {
        let mut tid = 0u16;
        while !polling.load(Ordering::Relaxed) {
            assert_eq!(
                transact(&mut m, &read_req(tid, 1, 7, 3)),
                read_reply(tid, 1, &[7, 8, 9])
            );
            tid = tid.wrapping_add(1);
            thread::sleep(Duration::from_millis(20));
        }
    });
    // The browser trusts the gateway's key (its SubjectPublicKeyInfo's SHA-256).
    let spki = Command::new("sh")
        .arg("-c")
        .arg(format!(
            "openssl x509 -in {} -pubkey -noout | openssl pkey -pubin -outform der | openssl dgst -sha256 -binary | base64",
            pki.pem("gateway")
        ))
        .output()
        .unwrap();
    let spki = String::from_utf8(spki.stdout).unwrap().trim().to_owned();
    assert_eq!(spki.len(), 44, "{spki}");
    let trust = format!("--ignore-certificate-errors-spki-list={spki}");
    let profile = |n: &str| format!("--user-data-dir={}", dir.path().join(n).display());
    // The page is opened once first, so frames are recorded (while it is watched).
    let url = format!("https://operator:look%20at%20the%20plant@127.0.0.1:{port}/");
    browse(browser, &url, &[&trust, &profile("first"), "--dump-dom"]);
    let dom = browse(browser, &url, &[&trust, &profile("second"), "--dump-dom"]);
    let updates: u32 = text_after(&dom, "(update ").parse().unwrap();
    assert!(updates >= 2, "{updates} updates:\n{dom}");
    assert!(dom.contains(&format!("<h2>Line {line}")), "{dom}");
    assert!(
        dom.contains("00 00 00 06 01 03 00 07 00 03"),
        "a request's bytes: {dom}"
    );
    // Without credentials: nothing of the plant in the page, nor in the bytes.
    let plain = format!("https://127.0.0.1:{port}/");
    let dom = browse(
        browser,
        &plain,
        &[&trust, &profile("stranger"), "--dump-dom"],
    );
    for word in [line.as_str(), "Line ", "frames", "01 03"] {
        assert!(!dom.contains(word), "{word:?} without credentials:\n{dom}");
    }
    for path in ["/", "/status.json"] {
        let out = Command::new("curl")
            .args(["-sS", "-i", "--cacert", &pki.pem("ca")])
            .arg(format!("https://127.0.0.1:{port}{path}"))
            .output()
            .unwrap();
        let text = out.stdout;
        let at = text.windows(4).position(|w| w == b"\r\n\r\n").unwrap();
        assert!(
            text.starts_with(b"HTTP/1.1 401 Unauthorized\r\n"),
            "{}",
            String::from_utf8_lossy(&text)
        );
        assert_eq!(
            &text[at + 4..],
            b"401 Unauthorized: a user and password are needed here\n"
        );
    }
    stop.store(true, Ordering::Relaxed);
    master.join().expect("the master was answered throughout");
    gw.stop();
}
