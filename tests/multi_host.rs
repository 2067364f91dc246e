//! Several hosts for real: three `ctrecon worker` processes, each in a network namespace of its own (made
//! by the test: `ip netns`, a veth pair per namespace on a bridge, a private /24), reach the PostgreSQL job
//! database and the S3 server (s3s-fs) at the bridge's address, so their traffic crosses an interface; an
//! API process on the host side queues the jobs, the namespaced workers run them, and the results are in
//! the bucket. A namespace cannot reach the host's loopback, so nothing goes around the link.
//!
//! Needs root and `ip` (iproute2); elsewhere it prints one skip line, unless `CTRECON_REQUIRE_PEERS=1`,
//! where it fails. Namespaces, links and the bridge are named uniquely per run and removed by a drop guard.

use crate::cluster;
use crate::common;
use crate::roles;
use crate::s3;

use std::process::Command;

use common::parallel_geometry;
use roles::{Process, api, fbp, on, sha256_of, sirt, worker};

/// Run `ip ARGS`; the error carries its stderr.
fn ip(args: &[&str]) -> Result<(), String> {
    let out = Command::new("ip")
        .args(args)
        .output()
        .map_err(|e| format!("ip: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "ip {}: {}",
            args.join(" "),
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

/// The test's network: a bridge on the host holding `<net>.1/24`, and per namespace a veth pair whose
/// host end is on the bridge and whose other end is `<net>.<10 + i>/24` in the namespace. Removed on drop.
struct Net {
    /// The first three octets of the /24, as `10.213.7`.
    net: String,
    bridge: String,
    namespaces: Vec<String>,
    /// The host end of each namespace's link.
    links: Vec<String>,
}

impl Drop for Net {
    fn drop(&mut self) {
        for ns in &self.namespaces {
            let _ = ip(&["netns", "del", ns]);
        }
        for link in &self.links {
            let _ = ip(&["link", "del", link]);
        }
        let _ = ip(&["link", "del", &self.bridge]);
    }
}

impl Net {
    fn host(&self) -> String {
        format!("{}.1", self.net)
    }

    fn address(&self, i: usize) -> String {
        format!("{}.{}", self.net, 10 + i)
    }

    /// Bytes that crossed the host end of namespace `i`'s link, both ways.
    fn bytes(&self, i: usize) -> u64 {
        ["rx_bytes", "tx_bytes"]
            .iter()
            .map(|f| {
                let p = format!("/sys/class/net/{}/statistics/{f}", self.links[i]);
                std::fs::read_to_string(p)
                    .ok()
                    .and_then(|t| t.trim().parse::<u64>().ok())
                    .unwrap_or(0)
            })
            .sum()
    }

    /// `command` run inside namespace `i`.
    fn inside(&self, i: usize, command: Command) -> Command {
        let mut c = Command::new("ip");
        c.args(["netns", "exec", &self.namespaces[i]])
            .arg(command.get_program())
            .args(command.get_args());
        for (k, v) in command.get_envs() {
            match v {
                Some(v) => c.env(k, v),
                None => c.env_remove(k),
            };
        }
        c
    }
}

/// A /24 of 10.213.0.0/16 that no interface of this host uses yet.
fn free_net() -> Result<String, String> {
    let out = Command::new("ip")
        .args(["-4", "-o", "addr", "show"])
        .output()
        .map_err(|e| format!("ip: {e}"))?;
    let used = String::from_utf8_lossy(&out.stdout).into_owned();
    let start = std::process::id() as usize;
    (0..250)
        .map(|k| format!("10.213.{}", 1 + (start + k) % 250))
        .find(|net| !used.contains(&format!("{net}.")))
        .ok_or_else(|| "no free /24 in 10.213.0.0/16".to_string())
}

/// Make the network for `n` namespaces, or say why it cannot be made.
fn make_net(n: usize) -> Result<Net, String> {
    let is_root = Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0");
    if !is_root {
        return Err("network namespaces need root".into());
    }
    let tag = format!("{:x}", std::process::id());
    let mut net = Net {
        net: free_net()?,
        bridge: format!("ctb{tag}"),
        namespaces: Vec::new(),
        links: Vec::new(),
    };
    ip(&["link", "add", &net.bridge, "type", "bridge"])?;
    ip(&[
        "addr",
        "add",
        &format!("{}/24", net.host()),
        "dev",
        &net.bridge,
    ])?;
    ip(&["link", "set", &net.bridge, "up"])?;
    for i in 0..n {
        let ns = format!("ctrecon-{tag}-{i}");
        ip(&["netns", "add", &ns])?;
        net.namespaces.push(ns.clone());
        let (host_end, ns_end) = (format!("cth{tag}{i}"), format!("ctw{tag}{i}"));
        ip(&[
            "link", "add", &host_end, "type", "veth", "peer", "name", &ns_end, "netns", &ns,
        ])?;
        net.links.push(host_end.clone());
        ip(&["link", "set", &host_end, "master", &net.bridge])?;
        ip(&["link", "set", &host_end, "up"])?;
        let addr = format!("{}/24", net.address(i));
        ip(&["-n", &ns, "addr", "add", &addr, "dev", &ns_end])?;
        ip(&["-n", &ns, "link", "set", &ns_end, "up"])?;
        ip(&["-n", &ns, "link", "set", "lo", "up"])?;
    }
    Ok(net)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn workers_in_network_namespaces_reach_the_database_and_the_bucket_across_a_link() {
    let test = "workers_in_network_namespaces";
    let net = match make_net(3) {
        Ok(net) => net,
        Err(why) => {
            assert!(
                std::env::var("CTRECON_REQUIRE_PEERS").as_deref() != Ok("1"),
                "{test}: {why}, and CTRECON_REQUIRE_PEERS=1"
            );
            eprintln!("skipped {test}: {why}");
            return;
        }
    };
    let host = net.host();
    let Some(pg) = cluster::cluster_on(test, &host, &format!("{}.0/24", net.net)) else {
        return;
    };
    let Some(s3) = s3::s3_on(test, &host) else {
        return;
    };
    let url = cluster::database_on(&pg, &host);

    // A namespace has a loopback of its own: the host's PostgreSQL is not there, only across the link.
    let probe = |target: &str| {
        let mut c = Command::new("timeout");
        c.args([
            "3",
            "bash",
            "-c",
            &format!("exec 3<>/dev/tcp/{target}/{}", pg.port),
        ]);
        net.inside(0, c)
            .stderr(std::process::Stdio::null())
            .status()
            .is_ok_and(|s| s.success())
    };
    assert!(!probe("127.0.0.1"), "the host's loopback is out of reach");
    assert!(probe(&host), "the database answers across the link");

    let api_dir = tempfile::tempdir().expect("dir");
    let a = api(s3.serve_to(on(api_dir.path(), &url)));
    let client = common::attach(&a.base);
    let dirs: Vec<tempfile::TempDir> = (0..3).map(|_| tempfile::tempdir().expect("dir")).collect();
    let before: Vec<u64> = (0..3).map(|i| net.bytes(i)).collect();
    let workers: Vec<Process> = (0..3)
        .map(|i| {
            let mut c = s3.serve_to(on(dirs[i].path(), &url));
            // The health port is on the test's private network, which has no tokens.
            c.env("CTRECON_ALLOW_INSECURE", "true");
            worker(net.inside(i, c), &net.address(i))
        })
        .collect();
    for (i, w) in workers.iter().enumerate() {
        assert!(
            w.base.starts_with(&format!("http://{}:", net.address(i))),
            "{}",
            w.base
        );
        let r = common::attach(&w.base).get("/readyz").await;
        assert_eq!(r.status(), 200, "worker {i} is ready across the link");
    }

    // Nine jobs queued on the host side run on the namespaced workers.
    let flat = client.simulate(parallel_geometry(180, 96, 1.0), 28.0).await;
    let mut ids = Vec::new();
    for k in 0..9 {
        let body = if k % 2 == 0 {
            fbp(&flat)
        } else {
            sirt(&flat, 5)
        };
        ids.push(
            client.submit(&body).await["id"]
                .as_str()
                .expect("id")
                .to_string(),
        );
    }
    for id in &ids {
        let done = client.finish(id).await;
        assert_eq!(done["status"], "succeeded", "{done}");
        assert_eq!(done["attempts"], 1, "{done}");
        let sha = done["result"]["volume"]["sha256"].as_str().expect("sha");
        assert_eq!(
            sha256_of(&s3.object_file(&format!("results/{id}/volume.npy"))),
            sha
        );
    }
    let mut ran = Vec::new();
    for w in &workers {
        ran.push(
            w.metric("ctrecon_jobs_finished_total", "status=\"succeeded\"")
                .await,
        );
    }
    eprintln!("jobs per namespaced worker: {ran:?}");
    assert_eq!(ran.iter().sum::<f64>(), 9.0, "{ran:?}");
    assert_eq!(a.metric("ctrecon_jobs_finished_total", "").await, 0.0);

    // Each worker's traffic crossed its link: a worker that ran a job fetched the dataset (180 × 96 float32,
    // 69 kB) and put its results through it.
    let dataset_bytes: u64 = 180 * 96 * 4;
    for i in 0..3 {
        let crossed = net.bytes(i).saturating_sub(before[i]);
        eprintln!("link {i}: {crossed} bytes");
        if ran[i] >= 1.0 {
            assert!(crossed > dataset_bytes, "link {i}: {crossed} bytes");
            assert!(
                dirs[i]
                    .path()
                    .join(format!("datasets/{flat}.npy"))
                    .is_file()
            );
        }
    }
    assert_eq!(s3.unfinished(), Vec::<String>::new());
}
