//! The Zenoh side of a bridge: the session (peer mode, only the endpoints given, no discovery),
//! the keys of one swarm, and the outbox every forwarded message leaves by (with an optional
//! emulated delay and loss of a real network).

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow};
use rand::Rng;
use zenoh::pubsub::Publisher;
use zenoh::qos::CongestionControl;
use zenoh::{Config, Session, Wait};

/// How long a silent link takes to be declared lost (Zenoh's lease; its default is 10 s).
const LEASE_MS: u64 = 2000;
/// The longest pause between two attempts to reach a `--connect` endpoint.
const RECONNECT_MAX_MS: u64 = 1000;

/// Where a bridge listens and whom it dials.
#[derive(Debug, Clone, Default)]
pub struct Endpoints {
    /// Zenoh locators this bridge accepts links on, e.g. `tcp/127.0.0.1:7447`.
    pub listen: Vec<String>,
    /// Zenoh locators this bridge dials (and redials after a lost link).
    pub connect: Vec<String>,
    /// A Zenoh JSON5 configuration (TLS, access control); its endpoints are replaced by these.
    pub config_file: Option<std::path::PathBuf>,
}

/// Opens the bridge's Zenoh session: peer mode, listening only on `listen` (never on all
/// interfaces by default), dialling `connect`, no multicast or gossip discovery.
pub fn open_session(endpoints: &Endpoints) -> Result<Session> {
    let mut config = match &endpoints.config_file {
        Some(path) => Config::from_file(path).map_err(|err| anyhow!("zenoh config {}: {err}", path.display()))?,
        None => Config::default(),
    };
    let set = |config: &mut Config, key: &str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|err| anyhow!("zenoh config {key} = {value}: {err}"))
    };
    set(&mut config, "mode", "\"peer\"".into())?;
    // Exactly the endpoints given, whatever a file says (none: listen nowhere, where Zenoh's
    // default is every interface); a file brings TLS and access control.
    set(&mut config, "listen/endpoints", json_list(&endpoints.listen))?;
    set(&mut config, "connect/endpoints", json_list(&endpoints.connect))?;
    set(&mut config, "scouting/multicast/enabled", "false".into())?;
    set(&mut config, "scouting/gossip/enabled", "false".into())?;
    set(&mut config, "transport/link/tx/lease", LEASE_MS.to_string())?;
    set(
        &mut config,
        "connect/retry",
        format!("{{period_init_ms: 250, period_max_ms: {RECONNECT_MAX_MS}, period_increase_factor: 2}}"),
    )?;
    zenoh::open(config)
        .wait()
        .map_err(|err| anyhow!("cannot open the zenoh session: {err}"))
}

fn json_list(items: &[String]) -> String {
    let quoted: Vec<String> = items.iter().map(|item| format!("{item:?}")).collect();
    format!("[{}]", quoted.join(","))
}

/// The Zenoh keys of one swarm, named by the run id of its sim's host.
#[derive(Debug, Clone)]
pub struct Keys {
    prefix: String,
}

impl Keys {
    /// Keys of the swarm whose sim runs under `swarm_run_id`.
    pub fn new(swarm_run_id: &str) -> Self {
        Self {
            prefix: format!("formation/{swarm_run_id}"),
        }
    }

    /// sim -> robot `agent`: its observations.
    pub fn observation(&self, agent: usize) -> String {
        format!("{}/agent/{agent}/observation", self.prefix)
    }

    /// Every robot's observations.
    pub fn observations(&self) -> String {
        format!("{}/agent/*/observation", self.prefix)
    }

    /// robot `agent` -> sim: its commands.
    pub fn command(&self, agent: usize) -> String {
        format!("{}/agent/{agent}/command", self.prefix)
    }

    /// Every robot's commands.
    pub fn commands(&self) -> String {
        format!("{}/agent/*/command", self.prefix)
    }

    /// critic -> robots: actor `index`'s weights.
    pub fn weights(&self, index: usize) -> String {
        format!("{}/actor/{index}/weights", self.prefix)
    }

    /// Every actor's weights.
    pub fn all_weights(&self) -> String {
        format!("{}/actor/*/weights", self.prefix)
    }

    /// Liveliness of the bridge on the sim's host.
    pub fn sim_host(&self) -> String {
        format!("{}/hosts/sim", self.prefix)
    }

    /// Liveliness of a robot host's bridge serving robot `agent`.
    pub fn robot_host(&self, agent: usize) -> String {
        format!("{}/hosts/robot/{agent}", self.prefix)
    }

    /// Every robot host's liveliness.
    pub fn robot_hosts(&self) -> String {
        format!("{}/hosts/robot/*", self.prefix)
    }

    /// The index in `key` after `segment` (`.../agent/2/command` -> 2 for `agent`).
    pub fn index_after(key: &str, segment: &str) -> Option<usize> {
        let mut parts = key.split('/');
        parts.find(|part| *part == segment)?;
        parts.next()?.parse().ok()
    }
}

/// An emulated network between the bridges: each message leaves `delay` late, or is lost with
/// probability `loss` (both 0: a message leaves at once).
#[derive(Debug, Clone, Copy, Default)]
pub struct NetEmulation {
    /// One-way delay added to every message this bridge sends.
    pub delay: Duration,
    /// Probability that a message this bridge sends is dropped.
    pub loss: f64,
}

/// A message on the delay line: when it is due, its key's index, its bytes.
type Delayed = (Instant, usize, Vec<u8>);

/// The emulated network's messages in flight.
#[derive(Default)]
struct DelayLine {
    /// Messages not yet due, in due order.
    queue: VecDeque<Delayed>,
    /// Messages queued or being put: [`Outbox::flush`] waits for 0.
    pending: usize,
}

/// Where forwarded messages leave: one Zenoh publisher per key, sending at once or through the
/// emulated network's delay line.
pub struct Outbox {
    publishers: Vec<Publisher<'static>>,
    emulation: NetEmulation,
    line: Mutex<DelayLine>,
    /// Wakes the delay line: a message was queued.
    queued: Condvar,
    /// Wakes [`Outbox::flush`]: the delay line is empty.
    drained: Condvar,
    /// Messages the emulated network lost.
    pub lost: AtomicU64,
}

impl Outbox {
    /// Publishers for `keys` (sent to by index), express (no batching: a tick waits on them) and
    /// dropping rather than blocking when the link is congested or down.
    pub fn new(session: &Session, keys: &[String], emulation: NetEmulation) -> Result<Arc<Self>> {
        let publishers = keys
            .iter()
            .map(|key| {
                session
                    .declare_publisher(key.clone())
                    .congestion_control(CongestionControl::Drop)
                    .express(true)
                    .wait()
                    .map_err(|err| anyhow!("cannot declare the zenoh publisher {key}: {err}"))
            })
            .collect::<Result<Vec<_>>>()?;
        let outbox = Arc::new(Self {
            publishers,
            emulation,
            line: Mutex::new(DelayLine::default()),
            queued: Condvar::new(),
            drained: Condvar::new(),
            lost: AtomicU64::new(0),
        });
        if !emulation.delay.is_zero() {
            let line = Arc::clone(&outbox);
            std::thread::Builder::new()
                .name("net-delay".into())
                .spawn(move || deliver_when_due(&line))
                .context("cannot start the delay line")?;
        }
        Ok(outbox)
    }

    /// Sends `bytes` on the key at `key_index`.
    pub fn send(&self, key_index: usize, bytes: &[u8]) -> Result<()> {
        if self.emulation.loss > 0.0 && rand::rng().random_bool(self.emulation.loss.min(1.0)) {
            self.lost.fetch_add(1, Ordering::Relaxed);
            return Ok(());
        }
        if self.emulation.delay.is_zero() {
            return self.put(key_index, bytes);
        }
        let due = Instant::now() + self.emulation.delay;
        let mut line = self.line.lock().map_err(|_| anyhow!("delay line poisoned"))?;
        line.queue.push_back((due, key_index, bytes.to_vec()));
        line.pending += 1;
        self.queued.notify_one();
        Ok(())
    }

    /// Waits until every message on the delay line has left (at once without a delay), or
    /// until the delay and a second more have passed.
    pub fn flush(&self) -> Result<()> {
        let line = self.line.lock().map_err(|_| anyhow!("delay line poisoned"))?;
        let bound = self.emulation.delay + Duration::from_secs(1);
        let (line, _) = self
            .drained
            .wait_timeout_while(line, bound, |line| line.pending > 0)
            .map_err(|_| anyhow!("delay line poisoned"))?;
        anyhow::ensure!(
            line.pending == 0,
            "{} messages still on the delay line after {:.1} s",
            line.pending,
            bound.as_secs_f64()
        );
        Ok(())
    }

    fn put(&self, key_index: usize, bytes: &[u8]) -> Result<()> {
        self.publishers[key_index]
            .put(bytes)
            .wait()
            .map_err(|err| anyhow!("zenoh put failed: {err}"))
    }
}

/// The delay line: sends each queued message when it is due (the delay is constant, so the
/// queue is in due order), sleeping on a condition variable in between, and wakes a flush once
/// nothing is pending. Lives as long as the bridge.
fn deliver_when_due(outbox: &Outbox) {
    loop {
        let Ok(mut line) = outbox.line.lock() else { return };
        let now = Instant::now();
        match line.queue.front().map(|(due, _, _)| *due) {
            Some(due) if due <= now => {
                let Some((_, key_index, bytes)) = line.queue.pop_front() else {
                    continue;
                };
                drop(line);
                let _ = outbox.put(key_index, &bytes);
                let Ok(mut line) = outbox.line.lock() else { return };
                line.pending = line.pending.saturating_sub(1);
                if line.pending == 0 {
                    outbox.drained.notify_all();
                }
            }
            Some(due) => drop(outbox.queued.wait_timeout(line, due - now)),
            None => drop(outbox.queued.wait(line)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_name_the_swarm_and_give_their_index_back() {
        let keys = Keys::new("r123456p42");
        assert_eq!(keys.command(2), "formation/r123456p42/agent/2/command");
        assert_eq!(Keys::index_after(&keys.command(2), "agent"), Some(2));
        assert_eq!(Keys::index_after(&keys.weights(0), "actor"), Some(0));
        assert_eq!(Keys::index_after("formation/x/agent/two/command", "agent"), None);
        assert_eq!(json_list(&["tcp/127.0.0.1:7447".into()]), r#"["tcp/127.0.0.1:7447"]"#);
    }

    #[test]
    fn a_flush_returns_once_every_delayed_message_has_left() {
        let session = open_session(&Endpoints::default()).expect("session");
        let key = "formation/flush-test/agent/0/observation".to_string();
        let received = session.declare_subscriber(key.clone()).wait().expect("subscriber");
        let emulation = NetEmulation {
            delay: Duration::from_millis(50),
            loss: 0.0,
        };
        let outbox = Outbox::new(&session, std::slice::from_ref(&key), emulation).expect("outbox");
        for byte in 0..3u8 {
            outbox.send(0, &[byte]).expect("send");
        }
        assert!(
            received.try_recv().expect("open").is_none(),
            "nothing leaves before its delay"
        );
        outbox.flush().expect("flush");
        let got: Vec<Vec<u8>> = std::iter::from_fn(|| received.try_recv().expect("open"))
            .map(|sample| sample.payload().to_bytes().to_vec())
            .collect();
        assert_eq!(got, [[0], [1], [2]]);
        session.close().wait().expect("close");
    }

    /// Whether the access control of the Zenoh config `file` lets `subject` (a certificate's
    /// common name) exchange `message` on `key` in `flow`, as Zenoh decides it: deny by default,
    /// allowed when a policy naming the subject has an allow rule with that flow and message
    /// whose key expressions include the key (a subscriber's declared key, wildcards and all).
    fn acl_allows(file: &str, subject: &str, flow: &str, message: &str, key: &str) -> bool {
        use zenoh::key_expr::KeyExpr;
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../configs/zenoh")
            .join(file);
        let config = Config::from_file(&path).unwrap_or_else(|err| panic!("{}: {err}", path.display()));
        let get = |what: &str| -> serde_json::Value {
            serde_json::from_str(&config.get_json(&format!("access_control/{what}")).expect(what)).expect("json")
        };
        assert_eq!(get("enabled"), true);
        assert_eq!(get("default_permission"), "deny");
        let (rules, subjects, policies) = (get("rules"), get("subjects"), get("policies"));
        let list = |value: &serde_json::Value| -> Vec<String> {
            value.as_array().map_or_else(Vec::new, |items| {
                items
                    .iter()
                    .filter_map(|item| item.as_str().map(str::to_string))
                    .collect()
            })
        };
        let key = KeyExpr::new(key.to_string()).expect("key");
        let subject_ids: Vec<String> = subjects
            .as_array()
            .expect("subjects")
            .iter()
            .filter(|s| list(&s["cert_common_names"]).iter().any(|cn| cn == subject))
            .map(|s| s["id"].as_str().expect("id").to_string())
            .collect();
        let rule_ids: Vec<String> = policies
            .as_array()
            .expect("policies")
            .iter()
            .filter(|p| list(&p["subjects"]).iter().any(|id| subject_ids.contains(id)))
            .flat_map(|p| list(&p["rules"]))
            .collect();
        rules.as_array().expect("rules").iter().any(|rule| {
            let flows = list(&rule["flows"]);
            rule_ids.iter().any(|id| rule["id"] == id.as_str())
                && rule["permission"] == "allow"
                && (flows.is_empty() || flows.iter().any(|f| f == flow))
                && list(&rule["messages"]).iter().any(|m| m == message)
                && list(&rule["key_exprs"])
                    .iter()
                    .any(|k| KeyExpr::new(k.clone()).expect("rule key").includes(&key))
        })
    }

    #[test]
    fn the_access_control_example_gives_each_robot_host_only_its_own_robots_keys() {
        let keys = Keys::new("r123456p42");
        let sim = |subject: &str, flow: &str, message: &str, key: &str| {
            acl_allows("sim-host.json5", subject, flow, message, key)
        };
        // What the sim's bridge exchanges with robot 2's host (sim_side.rs, robot_side.rs).
        for (flow, message, key) in [
            ("egress", "put", keys.observation(2)),
            ("egress", "put", keys.weights(0)),
            ("egress", "declare_subscriber", keys.commands()),
            ("egress", "liveliness_token", keys.sim_host()),
            ("ingress", "put", keys.command(2)),
            ("ingress", "declare_subscriber", keys.observations()),
            ("ingress", "declare_subscriber", keys.all_weights()),
            ("ingress", "liveliness_token", keys.robot_host(2)),
        ] {
            assert!(sim("robot-2", flow, message, &key), "{flow} {message} {key}");
        }
        // Robot 2's host cannot command robot 0 nor get its observations; robot 0's can.
        assert!(!sim("robot-2", "ingress", "put", &keys.command(0)));
        assert!(!sim("robot-2", "egress", "put", &keys.observation(0)));
        assert!(sim("robot-0", "ingress", "put", &keys.command(0)));
        assert!(!sim("robot-0", "ingress", "put", &keys.command(2)));
        assert!(!sim("stranger", "ingress", "put", &keys.command(2)));
        // Robot 2's host, towards the sim's host.
        let robot = |flow: &str, message: &str, key: &str| acl_allows("robot-2.json5", "sim-host", flow, message, key);
        for (flow, message, key) in [
            ("ingress", "put", keys.observation(2)),
            ("ingress", "put", keys.weights(0)),
            ("ingress", "declare_subscriber", keys.commands()),
            ("ingress", "liveliness_token", keys.sim_host()),
            ("egress", "put", keys.command(2)),
            ("egress", "declare_subscriber", keys.observations()),
            ("egress", "declare_subscriber", keys.all_weights()),
            ("egress", "liveliness_token", keys.robot_host(2)),
        ] {
            assert!(robot(flow, message, &key), "{flow} {message} {key}");
        }
        assert!(!robot("egress", "put", &keys.command(0)));
    }
}
