//! Graphs split over hosts: each host is a network namespace of its own (its own network
//! stack, joined to the other by a veth pair), running `gprflow launch --host NAME`. The
//! tests set the namespaces up and tear them down themselves; they need root and `ip`.
//! Addresses are 10.77.K.1 and 10.77.K.2, only inside those namespaces.

// Tests spawn helper threads and processes; names would add nothing.
#![allow(clippy::disallowed_methods)]

mod common;

use std::path::Path;
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use common::{BASEMENT, GPRFLOW, gprflow, repo};

fn ip(args: &[&str]) {
    let o = Command::new("ip").args(args).output().expect("`ip` runs (iproute2)");
    assert!(
        o.status.success(),
        "ip {}: {} (these tests need root)",
        args.join(" "),
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Two network namespaces, `robot` at 10.77.K.1 and `base` at 10.77.K.2, joined by a veth
/// pair; removed on drop.
struct Hosts {
    robot: String,
    base: String,
    robot_if: String,
    net: u8,
}

impl Hosts {
    fn new(net: u8) -> Self {
        let id = std::process::id() % 100_000;
        let hosts = Self {
            robot: format!("gfz{id}n{net}r"),
            base: format!("gfz{id}n{net}b"),
            robot_if: format!("gz{id}n{net}r"),
            net,
        };
        let base_if = format!("gz{id}n{net}b");
        // a namespace left by an earlier run that was killed
        for ns in [&hosts.robot, &hosts.base] {
            let _ = Command::new("ip")
                .args(["netns", "del", ns])
                .stderr(Stdio::null())
                .status();
        }
        ip(&["netns", "add", &hosts.robot]);
        ip(&["netns", "add", &hosts.base]);
        ip(&["link", "add", &hosts.robot_if, "type", "veth", "peer", "name", &base_if]);
        for (ns, dev, addr) in [
            (&hosts.robot, &hosts.robot_if, hosts.robot_addr()),
            (&hosts.base, &base_if, hosts.base_addr()),
        ] {
            ip(&["link", "set", dev, "netns", ns]);
            ip(&["-n", ns, "addr", "add", &format!("{addr}/30"), "dev", dev]);
            ip(&["-n", ns, "link", "set", dev, "up"]);
            ip(&["-n", ns, "link", "set", "lo", "up"]);
        }
        hosts
    }

    fn robot_addr(&self) -> String {
        format!("10.77.{}.1", self.net)
    }

    fn base_addr(&self) -> String {
        format!("10.77.{}.2", self.net)
    }

    /// Starts `gprflow ARGS` inside namespace `ns`.
    fn spawn(&self, ns: &str, args: &[&str], log: &Path) -> Child {
        let file = std::fs::File::create(log).expect("log file");
        Command::new("ip")
            .args(["netns", "exec", ns, GPRFLOW])
            .args(args)
            .current_dir(repo())
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(file)
            .spawn()
            .expect("ip netns exec runs")
    }
}

impl Drop for Hosts {
    fn drop(&mut self) {
        // deleting a namespace deletes its end of the veth pair, and so the pair
        for ns in [&self.robot, &self.base] {
            let _ = Command::new("ip").args(["netns", "del", ns]).status();
        }
    }
}

/// Waits for `child` up to `limit`; kills it past that.
fn finish(mut child: Child, limit: Duration, log: &Path) -> (bool, String) {
    let start = Instant::now();
    let ok = loop {
        if let Some(status) = child.try_wait().expect("wait") {
            break status.success();
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            break false;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    (ok, std::fs::read_to_string(log).unwrap_or_default())
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// `graph`'s text with its `record:` line replaced and a `hosts:` section added.
fn split_graph(graph: &str, record: &str, hosts: &str) -> String {
    let text = std::fs::read_to_string(repo().join(graph)).expect("graph file");
    let kept: Vec<&str> = text.lines().filter(|l| !l.starts_with("record:")).collect();
    format!("{}\n{record}\n{hosts}", kept.join("\n"))
}

/// Runs `graph_file` on both hosts (robot without recording, base recording to `record`).
fn run_split(hosts: &Hosts, graph_file: &Path, record: &Path, extra: &[&str], limit: Duration) -> [(bool, String); 2] {
    let dir = record.parent().expect("dir");
    let graph = graph_file.to_str().expect("utf8");
    // zenoh's transport log says when sessions close and open again
    let log = ["--log", "info,zenoh_transport=debug"];
    let mut robot_args = [log.as_slice(), &["launch", graph, "--host", "robot"]].concat();
    robot_args.extend(extra);
    let mut base_args = [
        log.as_slice(),
        &[
            "launch",
            graph,
            "--host",
            "base",
            "--record",
            record.to_str().expect("utf8"),
        ],
    ]
    .concat();
    base_args.extend(extra);
    let robot = hosts.spawn(&hosts.robot, &robot_args, &dir.join("robot.log"));
    let base = hosts.spawn(&hosts.base, &base_args, &dir.join("base.log"));
    [
        finish(robot, limit, &dir.join("robot.log")),
        finish(base, limit, &dir.join("base.log")),
    ]
}

fn assert_same(a: &Path, b: &Path) {
    let o = gprflow(&["diff", a.to_str().expect("utf8"), b.to_str().expect("utf8")]);
    assert!(o.status.success(), "the runs differ:\n{}", text(&o));
}

/// The localisation pipeline with the register -> estimate -> register feedback cycle cut
/// across the two hosts records exactly what it records on one machine.
#[test]
fn localisation_split_over_two_hosts_records_what_one_host_records() {
    let dir = tempfile::tempdir().expect("tempdir");
    let single = dir.path().join("single.mcap");
    let o = gprflow(&[
        "launch",
        "graphs/localize.yaml",
        "--record",
        single.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", text(&o));

    let hosts = Hosts::new(1);
    let graph = dir.path().join("localize-hosts.yaml");
    let text = split_graph(
        "graphs/localize.yaml",
        r#"record: { topics: ["estimate/*", "register/*"], host: base }"#,
        &format!(
            "hosts:\n  robot: {{ nodes: [ingest, dsp, submap, filter, register], zenoh: {{ listen: [tcp/{r}:7447] }} }}\n  base: {{ nodes: [estimate], zenoh: {{ connect: [tcp/{r}:7447] }} }}\n",
            r = hosts.robot_addr()
        ),
    );
    std::fs::write(&graph, text).expect("graph");
    let split = dir.path().join("split.mcap");
    let [(robot_ok, robot_log), (base_ok, base_log)] = run_split(&hosts, &graph, &split, &[], Duration::from_secs(240));
    assert!(robot_ok && base_ok, "robot:\n{robot_log}\nbase:\n{base_log}");
    // imu, wheel, truth and registrations go to base, the estimate comes back as feedback
    for route in [
        "`ingest/imu` to host `base`",
        "`register/registration` to host `base`",
        "`estimate/state` from host `base`",
    ] {
        assert!(robot_log.contains(route), "robot relays {route}:\n{robot_log}");
    }
    assert_same(&single, &split);
}

/// The link goes down for 4 s in the middle of a paced replay (longer than the 1 s zenoh
/// lease, so zenoh closes the session and opens a new one when the link is back; what was
/// sent meanwhile is lost to zenoh): the run completes by itself, the bridge sent the lost
/// frames again, and the recording equals the one-host run.
#[test]
fn a_link_cut_for_seconds_loses_nothing() {
    let dir = tempfile::tempdir().expect("tempdir");
    let hosts = Hosts::new(2);
    let nodes = format!(
        "name: cut\nnodes:\n  ingest: {{ stage: ingest, params: {{ source: {BASEMENT}, pace: recorded, speed: 10.0 }} }}\n  dsp: {{ stage: dsp, inputs: {{ trace: ingest/gpr }} }}\n"
    );
    let record = r#"record: { topics: ["*"], host: base }"#;
    let hosts_text = format!(
        "hosts:\n  robot: {{ nodes: [ingest], zenoh: {{ listen: [tcp/{r}:7447], lease_ms: 1000 }} }}\n  base: {{ nodes: [dsp], zenoh: {{ connect: [tcp/{r}:7447], lease_ms: 1000 }} }}\n",
        r = hosts.robot_addr()
    );
    let single_graph = dir.path().join("single.yaml");
    std::fs::write(&single_graph, format!("{nodes}record: {{ topics: [\"*\"] }}\n")).expect("graph");
    let single = dir.path().join("single.mcap");
    let o = gprflow(&[
        "launch",
        single_graph.to_str().expect("utf8"),
        "--record",
        single.to_str().expect("utf8"),
    ]);
    assert!(o.status.success(), "{}", text(&o));

    let graph = dir.path().join("cut.yaml");
    std::fs::write(&graph, format!("{nodes}{record}\n{hosts_text}")).expect("graph");
    let split = dir.path().join("split.mcap");
    let cutter = {
        let (robot, robot_if) = (hosts.robot.clone(), hosts.robot_if.clone());
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_secs(3));
            ip(&["-n", &robot, "link", "set", &robot_if, "down"]);
            let cut = Instant::now();
            std::thread::sleep(Duration::from_secs(4));
            ip(&["-n", &robot, "link", "set", &robot_if, "up"]);
            cut.elapsed()
        })
    };
    let started = Instant::now();
    let [(robot_ok, robot_log), (base_ok, base_log)] = run_split(&hosts, &graph, &split, &[], Duration::from_secs(120));
    let wall = started.elapsed();
    let down = cutter.join().expect("cutter");
    assert!(robot_ok && base_ok, "robot:\n{robot_log}\nbase:\n{base_log}");
    // 135 s of recording at 10x: the run was still going when the link came back
    assert!(
        wall > Duration::from_secs(3) + down,
        "run took {wall:?}, link down {down:?}"
    );
    // zenoh closed the session and opened a new one
    for side in [&robot_log, &base_log] {
        assert!(side.contains("Closing transport"), "session closed:\n{side}");
        assert_eq!(
            side.matches("New transport opened").count(),
            2,
            "session reopened:\n{side}"
        );
    }
    let resent: u64 = robot_log
        .lines()
        .filter(|l| l.contains("relayed route"))
        .filter_map(|l| l.split("resent=").nth(1))
        .filter_map(|n| n.split_whitespace().next()?.parse::<u64>().ok())
        .sum();
    assert!(resent > 0, "frames sent again:\n{robot_log}");
    assert_same(&single, &split);
}

/// A link that stays down fails the run with the topic and the frames not delivered.
#[test]
fn a_link_down_for_good_is_reported_with_topic_and_seqs() {
    let dir = tempfile::tempdir().expect("tempdir");
    let hosts = Hosts::new(3);
    let graph = dir.path().join("down.yaml");
    std::fs::write(
        &graph,
        format!(
            "name: down\nnodes:\n  ingest: {{ stage: ingest, params: {{ source: {BASEMENT}, pace: recorded, speed: 10.0 }} }}\n  dsp: {{ stage: dsp, inputs: {{ trace: ingest/gpr }} }}\nrecord: {{ topics: [\"dsp/*\"], host: base }}\nhosts:\n  robot: {{ nodes: [ingest], zenoh: {{ listen: [tcp/{r}:7447], link_timeout_s: 3 }} }}\n  base: {{ nodes: [dsp], zenoh: {{ connect: [tcp/{r}:7447], link_timeout_s: 3 }} }}\n",
            r = hosts.robot_addr()
        ),
    )
    .expect("graph");
    let split = dir.path().join("split.mcap");
    let cutter = {
        let (robot, robot_if) = (hosts.robot.clone(), hosts.robot_if.clone());
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_secs(3));
            ip(&["-n", &robot, "link", "set", &robot_if, "down"]);
        })
    };
    let [(robot_ok, robot_log), (base_ok, base_log)] = run_split(&hosts, &graph, &split, &[], Duration::from_secs(60));
    cutter.join().expect("cutter");
    assert!(
        !robot_ok && !base_ok,
        "both sides fail:\nrobot:\n{robot_log}\nbase:\n{base_log}"
    );
    // the sending side names the topic and the seqs it could not deliver
    let lost = robot_log
        .lines()
        .find(|l| l.contains("link down") && l.contains("ingest/gpr"))
        .unwrap_or_else(|| panic!("robot reports the loss:\n{robot_log}"));
    assert!(lost.contains("data frames seq"), "{lost}");
    eprintln!("reported: {lost}");
    assert!(
        base_log.contains("link down"),
        "base reports the silent link:\n{base_log}"
    );
}

/// Mutual TLS between the hosts, each allowing only the other's certificate name: the run
/// works; a host whose certificate name is not allowed gets nothing and the run fails with
/// the reason.
#[test]
fn tls_with_an_allow_list_admits_only_the_named_host() {
    let dir = tempfile::tempdir().expect("tempdir");
    let hosts = Hosts::new(4);
    let certs = dir.path().join("certs");
    let o = Command::new(repo().join("tools/scripts/make-certs.sh"))
        .arg(&certs)
        .arg(format!("robot={}", hosts.robot_addr()))
        .arg(format!("base={}", hosts.base_addr()))
        .arg(format!("intruder={}", hosts.base_addr()))
        .output()
        .expect("make-certs.sh runs");
    assert!(o.status.success(), "{}", text(&o));
    let c = certs.display();
    let graph_for = |base_cert: &str| {
        format!(
            "name: tls\nnodes:\n  gen: {{ stage: toy_source, params: {{ count: 300 }} }}\n  gain: {{ stage: toy_gain, inputs: {{ trace: gen/trace }} }}\nrecord: {{ topics: [\"*\"], host: base }}\nhosts:\n  robot:\n    nodes: [gen]\n    zenoh: {{ listen: [tls/{r}:7447], tls: {{ root_ca: {c}/ca.pem, certificate: {c}/robot.pem, private_key: {c}/robot.key }}, allow: [base] }}\n  base:\n    nodes: [gain]\n    zenoh: {{ connect: [tls/{r}:7447], tls: {{ root_ca: {c}/ca.pem, certificate: {c}/{base_cert}.pem, private_key: {c}/{base_cert}.key }}, allow: [robot] }}\n",
            r = hosts.robot_addr()
        )
    };
    let good = dir.path().join("good.yaml");
    std::fs::write(&good, graph_for("base")).expect("graph");
    let rec = dir.path().join("good.mcap");
    let [(robot_ok, robot_log), (base_ok, base_log)] = run_split(&hosts, &good, &rec, &[], Duration::from_secs(60));
    assert!(robot_ok && base_ok, "robot:\n{robot_log}\nbase:\n{base_log}");
    let o = gprflow(&["inspect", rec.to_str().expect("utf8"), "--json"]);
    assert!(text(&o).contains("gain/trace"), "{}", text(&o));

    let bad = dir.path().join("bad.yaml");
    std::fs::write(&bad, graph_for("intruder")).expect("graph");
    let rec = dir.path().join("bad.mcap");
    let [(robot_ok, robot_log), (base_ok, base_log)] = run_split(
        &hosts,
        &bad,
        &rec,
        &["--remote-timeout-s", "4"],
        Duration::from_secs(60),
    );
    assert!(!robot_ok && !base_ok, "robot:\n{robot_log}\nbase:\n{base_log}");
    assert!(
        robot_log.contains("host `base` did not subscribe"),
        "robot names the host that never came:\n{robot_log}"
    );
}

/// Bad host sections are refused before anything starts, naming file and key.
#[test]
fn bad_host_sections_are_refused_with_file_and_key() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cases = [
        ("zenoh: { listen: [udp/10.0.0.1:7447] }", "protocol `udp`"),
        ("zenoh: { listen: [tcp/10.0.0.1] }", "expected ADDRESS:PORT"),
        ("zenoh: { listen: [tls/10.0.0.1:7447] }", "needs the host's `tls:`"),
        ("zenoh: { mode: star }", "zenoh mode `star`"),
        ("zenoh: { allow: [base] }", "needs `tls`"),
        ("zenoh: { link_timeout_s: 0 }", "link_timeout_s 0"),
    ];
    for (i, (zenoh, expected)) in cases.iter().enumerate() {
        let graph = dir.path().join(format!("bad{i}.yaml"));
        std::fs::write(
            &graph,
            format!(
                "name: bad\nnodes:\n  gen: {{ stage: toy_source }}\nhosts:\n  robot: {{ nodes: [gen], {zenoh} }}\n"
            ),
        )
        .expect("graph");
        let o = gprflow(&["launch", graph.to_str().expect("utf8"), "--host", "robot"]);
        let out = text(&o);
        assert!(!o.status.success(), "{zenoh}: {out}");
        assert!(
            out.contains(&format!("bad{i}.yaml:5")),
            "{zenoh}: names file and line: {out}"
        );
        assert!(out.contains(expected), "{zenoh}: {out}");
    }
    // certificates that are not there, and recording asked of the wrong host
    let graph = dir.path().join("files.yaml");
    std::fs::write(
        &graph,
        "name: files\nnodes:\n  gen: { stage: toy_source }\n  gain: { stage: toy_gain, inputs: { trace: gen/trace } }\nrecord: { topics: [\"*\"], host: base }\nhosts:\n  robot: { nodes: [gen], zenoh: { listen: [tls/127.0.0.1:7447], tls: { root_ca: nope/ca.pem, certificate: nope/r.pem, private_key: nope/r.key } } }\n  base: { nodes: [gain], zenoh: { connect: [tcp/127.0.0.1:7447] } }\n",
    )
    .expect("graph");
    let g = graph.to_str().expect("utf8");
    let o = gprflow(&["launch", g, "--host", "robot"]);
    assert!(!o.status.success() && text(&o).contains("tls.root_ca"), "{}", text(&o));
    let o = gprflow(&["launch", g, "--host", "robot", "--record", "x.mcap"]);
    assert!(
        !o.status.success() && text(&o).contains("writes the recording, not `robot`"),
        "{}",
        text(&o)
    );
    let o = gprflow(&["launch", g, "--host", "base"]);
    assert!(
        !o.status.success() && text(&o).contains("give it --record FILE"),
        "{}",
        text(&o)
    );
}

/// What each host's launcher plans (`--dry-run`): the producer's output counts the bridge
/// as one subscriber per reading host, the reading host's bridge waits for its local
/// readers plus the recorder, and the recorder runs only on the recording host.
#[test]
fn each_host_plans_its_share_with_a_bridge() {
    let dir = tempfile::tempdir().expect("tempdir");
    let graph = dir.path().join("plan.yaml");
    std::fs::write(
        &graph,
        "name: plan\nnodes:\n  gen: { stage: toy_source }\n  gain: { stage: toy_gain, inputs: { trace: gen/trace } }\n  again: { stage: toy_gain, inputs: { trace: gain/trace } }\nrecord: { topics: [\"*\"], host: base }\nhosts:\n  robot: { nodes: [gen, again], zenoh: { listen: [tcp/127.0.0.1:7447] } }\n  base: { nodes: [gain], zenoh: { connect: [tcp/127.0.0.1:7447] } }\n",
    )
    .expect("graph");
    let plan = |args: &[&str]| -> serde_json::Value {
        let mut all = vec!["launch", graph.to_str().expect("utf8"), "--dry-run"];
        all.extend(args);
        let o = gprflow(&all);
        assert!(o.status.success(), "{}", text(&o));
        serde_json::from_slice(&o.stdout).expect("plan JSON")
    };
    let node = |plan: &serde_json::Value, name: &str| -> serde_json::Value {
        plan.as_array()
            .expect("nodes")
            .iter()
            .find(|n| n["node"] == name)
            .unwrap_or_else(|| panic!("no node {name} in {plan:#}"))
            .clone()
    };
    let names = |plan: &serde_json::Value| -> Vec<String> {
        plan.as_array()
            .expect("nodes")
            .iter()
            .map(|n| n["node"].as_str().expect("name").to_owned())
            .collect()
    };
    let routes = |bridge: &serde_json::Value| -> Vec<(String, String, String, u64)> {
        bridge["params"]["routes"]
            .as_array()
            .expect("routes")
            .iter()
            .map(|r| {
                (
                    r["topic"].as_str().expect("topic").to_owned(),
                    r["direction"].as_str().expect("direction").to_owned(),
                    r["peer"].as_str().expect("peer").to_owned(),
                    r["subscribers"].as_u64().expect("subscribers"),
                )
            })
            .collect()
    };

    let robot = plan(&["--host", "robot"]);
    assert_eq!(names(&robot), ["gen", "again", "__bridge"]);
    // gen/trace: read by gain on base (and recorded there): one bridge subscriber
    assert_eq!(node(&robot, "gen")["outputs"][0]["subscribers"], 1);
    assert_eq!(
        routes(&node(&robot, "__bridge")),
        [
            ("gen/trace".to_owned(), "out".to_owned(), "base".to_owned(), 0),
            ("gain/trace".to_owned(), "in".to_owned(), "base".to_owned(), 1),
            ("again/trace".to_owned(), "out".to_owned(), "base".to_owned(), 0),
        ]
    );
    let base = plan(&["--host", "base", "--record", "x.mcap"]);
    assert_eq!(names(&base), ["gain", "__record", "__bridge"]);
    // gain/trace: again on robot (bridge) and the recorder
    assert_eq!(node(&base, "gain")["outputs"][0]["subscribers"], 2);
    let recorder = node(&base, "__record");
    let recorded: Vec<&str> = recorder["inputs"]
        .as_array()
        .expect("inputs")
        .iter()
        .map(|i| i["topic"].as_str().expect("topic"))
        .collect();
    assert_eq!(recorded, ["gain/trace", "gen/trace", "again/trace"]);
    assert_eq!(
        routes(&node(&base, "__bridge")),
        [
            ("gen/trace".to_owned(), "in".to_owned(), "robot".to_owned(), 2),
            ("gain/trace".to_owned(), "out".to_owned(), "robot".to_owned(), 0),
            ("again/trace".to_owned(), "in".to_owned(), "robot".to_owned(), 1),
        ]
    );
    // all on one machine: no bridge
    assert_eq!(
        names(&plan(&["--record", "x.mcap"])),
        ["gen", "gain", "again", "__record"]
    );
}

/// The shipped two-host examples run as the README says, both hosts on this machine.
#[test]
fn the_shipped_two_host_examples_run_on_loopback() {
    let dir = tempfile::tempdir().expect("tempdir");
    let certs = dir.path().join("certs");
    let o = Command::new(repo().join("tools/scripts/make-certs.sh"))
        .arg(&certs)
        .args(["robot=127.0.0.1", "base=127.0.0.1"])
        .output()
        .expect("make-certs.sh runs");
    assert!(o.status.success(), "{}", text(&o));
    // the TLS example names out/certs; point it at this test's certificates
    let tls = std::fs::read_to_string(repo().join("graphs/toy-hosts-tls.yaml"))
        .expect("graph")
        .replace("out/certs", &certs.display().to_string());
    let tls_graph = dir.path().join("toy-hosts-tls.yaml");
    std::fs::write(&tls_graph, tls).expect("graph");
    for graph in [repo().join("graphs/toy-hosts.yaml"), tls_graph] {
        let g = graph.to_str().expect("utf8");
        let rec = dir.path().join("run.mcap");
        let robot = Command::new(GPRFLOW)
            .current_dir(repo())
            .args(["launch", g, "--host", "robot", "--set", "count=300"])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("robot starts");
        let base = gprflow(&[
            "launch",
            g,
            "--host",
            "base",
            "--set",
            "count=300",
            "--record",
            rec.to_str().expect("utf8"),
        ]);
        let robot = robot.wait_with_output().expect("robot ends");
        assert!(
            base.status.success() && robot.status.success(),
            "{g}:\nbase: {}\nrobot: {}",
            text(&base),
            text(&robot)
        );
        let single = dir.path().join("single.mcap");
        let o = gprflow(&[
            "launch",
            "graphs/toy.yaml",
            "--set",
            "count=300",
            "--record",
            single.to_str().expect("utf8"),
        ]);
        assert!(o.status.success(), "{}", text(&o));
        assert_same(&single, &rec);
    }
}
