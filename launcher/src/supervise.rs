//! Runs a [`Plan`]: preflight checks, the run directory and `run.json`, then every member as a
//! child process, each watched by a thread that reports its exit on one channel with the
//! launcher's signals (no polling). Members restart as the plan says; the primary sim's exit
//! ends the run; whatever happens, nothing of the run is left behind.

use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus, Stdio};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use formation_core::run_dir::write_atomically;
use formation_ipc::cli::{Mode, UPDATE_BUDGET_SPENT};
use formation_ipc::services::{RunIdentity, sweep_abandoned_runs};
use formation_ipc::summary::Summary;
use signal_hook::consts::{SIGINT, SIGTERM};
use signal_hook::iterator::Signals;

use crate::plan::{Member, Plan, Restart};

/// A member that dies sooner than this after its start counts as a quick death.
const QUICK_DEATH: Duration = Duration::from_secs(5);
/// Quick deaths in a row after which a member is not restarted and the run stops.
const QUICK_DEATHS_TO_GIVE_UP: u32 = 3;
/// After the primary sim's end, how long the others get to end on its end-of-run message.
const WIND_DOWN: Duration = Duration::from_secs(10);
/// In training, how much longer the critic then gets to score and save its last checkpoint
/// (its selection episodes take tens of seconds on a loaded 2-core machine).
const CRITIC_WIND_DOWN: Duration = Duration::from_secs(180);
/// An extra swarm's sim still running when the primary ends gets this long before Ctrl-C.
const EXTRA_SIM_GRACE: Duration = Duration::from_secs(2);
/// At the end, how long the run's files wait for clients still closing their ports.
const CLIENT_GRACE: Duration = Duration::from_secs(2);

/// What the supervisor waits for.
enum Event {
    /// A member exited.
    Exited(Member, ExitStatus),
    /// The launcher got SIGINT or SIGTERM.
    Interrupted,
    /// The critic printed `UPDATE_BUDGET_SPENT`: its `--updates` are done.
    UpdatesDone,
}

/// The running process set.
struct Supervisor<'a> {
    plan: &'a Plan,
    bin_dir: PathBuf,
    events: Receiver<Event>,
    sender: Sender<Event>,
    /// Pids of members that have not been seen to exit.
    running: HashMap<Member, u32>,
    /// Each member's last exit status.
    exits: HashMap<Member, ExitStatus>,
    /// When each member last started, and how many of its deaths in a row came soon after.
    starts: HashMap<Member, (Instant, u32)>,
    /// When `--minutes` (or train's default 30) is up, for the critic's countdown.
    ends_at: Option<Instant>,
    /// Threads copying the critic's output; they end with its pipes.
    tees: Vec<JoinHandle<()>>,
    /// The critic has said its `--updates` are done: the run is ending, it is not restarted.
    updates_done: bool,
}

/// What `formation-mcap` prints once its state subscriber exists (its `READY_LINE`).
const MCAP_READY_LINE: &str = "formation-mcap: ready";

/// Runs the plan to its end; returns the launcher's exit code.
pub fn launch(plan: &Plan) -> Result<u8> {
    let bin_dir = bin_dir()?;
    // Held for the launcher's whole life (released by the kernel however it ends): what tells
    // other launchers and clients that this run is alive, whichever PID namespace they are in.
    let _locks = plan
        .identities()
        .into_iter()
        .map(RunIdentity::hold_launcher_lock)
        .collect::<Result<Vec<_>>>()?;
    for (run_id, files) in sweep_abandoned_runs() {
        println!("removed {files} shared-memory files of run {run_id}, whose launcher is gone");
    }
    plan.write_launch_config()?;
    for (program, args) in plan.preflight() {
        let status = Command::new(bin_dir.join(program))
            .args(&args)
            .stdin(Stdio::null())
            .status()
            .with_context(|| format!("cannot run {}", bin_dir.join(program).display()))?;
        if !status.success() {
            return Ok(2);
        }
    }
    for run_dir in plan.run_dirs() {
        let logs = run_dir.join("logs");
        std::fs::create_dir_all(&logs).with_context(|| format!("cannot create {}", logs.display()))?;
    }
    let run_json = serde_json::to_vec_pretty(&plan.run_json())?;
    write_atomically(&plan.primary().run_dir.join("run.json"), &run_json)?;

    let (sender, events) = channel();
    let interrupts = sender.clone();
    let mut signals = Signals::new([SIGINT, SIGTERM]).context("cannot install the Ctrl-C handler")?;
    std::thread::spawn(move || {
        for _ in signals.forever() {
            if interrupts.send(Event::Interrupted).is_err() {
                break;
            }
        }
    });
    let minutes = plan
        .minutes
        .or((plan.mode == Mode::Train && plan.episodes.is_none() && plan.updates.is_none()).then_some(30.0));
    let mut supervisor = Supervisor {
        plan,
        bin_dir,
        events,
        sender,
        running: HashMap::new(),
        exits: HashMap::new(),
        starts: HashMap::new(),
        ends_at: minutes.map(|m| Instant::now() + Duration::from_secs_f64(m * 60.0)),
        tees: Vec::new(),
        updates_done: false,
    };
    let result = supervisor.run();
    supervisor.stop_all();
    // Every member has exited: the critic's last lines are out before the launcher's.
    for tee in supervisor.tees.drain(..) {
        let _ = tee.join();
    }
    for identity in plan.identities() {
        // A client (a Python env) whose ports outlive the sim removes those services itself.
        identity.wait_for_clients(CLIENT_GRACE);
        identity.remove_leftovers();
    }
    if !plan.primary().ros2.is_empty() {
        let run_dir = &plan.primary().run_dir;
        if let Err(err) = fold_ros2_counts(run_dir) {
            eprintln!("run_swarm.sh: the ROS 2 side's counts are not in summary.json: {err:#}");
        }
    }
    let code = result?;
    println!(
        "results: {} (summary.json, episodes.csv, config.toml, logs/)",
        plan.primary().run_dir.display()
    );
    Ok(code)
}

/// Adds the ROS 2 side's counts (`ros2.json`, written when it ends) to the sim's
/// `summary.json`; after every member has exited, so no other writer is left.
fn fold_ros2_counts(run_dir: &Path) -> Result<()> {
    #[derive(serde::Deserialize)]
    struct Counts {
        ros2_agents: Vec<usize>,
        ros2_twists: u64,
        ros2_twists_dropped: u64,
        ros2_twists_superseded: u64,
        ros2_twists_rejected: u64,
    }
    let read = |name: &str| {
        let path = run_dir.join(name);
        std::fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))
    };
    let counts: Counts = serde_json::from_str(&read("ros2.json")?).context("ros2.json")?;
    let mut summary: Summary = serde_json::from_str(&read("summary.json")?).context("summary.json")?;
    summary.ros2_agents = counts.ros2_agents;
    summary.ros2_twists = Some(counts.ros2_twists);
    summary.ros2_twists_dropped = Some(counts.ros2_twists_dropped);
    summary.ros2_twists_superseded = Some(counts.ros2_twists_superseded);
    summary.ros2_twists_rejected = Some(counts.ros2_twists_rejected);
    write_atomically(
        &run_dir.join("summary.json"),
        serde_json::to_string_pretty(&summary)?.as_bytes(),
    )
}

/// Where the member binaries are: `FORMATION_BIN_DIR`, else beside this launcher.
fn bin_dir() -> Result<PathBuf> {
    let dir = match std::env::var_os("FORMATION_BIN_DIR") {
        Some(dir) => PathBuf::from(dir),
        None => std::env::current_exe()?
            .parent()
            .context("the launcher has no directory")?
            .to_path_buf(),
    };
    for program in ["formation-sim", "formation-agent", "formation-critic"] {
        anyhow::ensure!(
            dir.join(program).is_file(),
            "missing binary {} (build with cargo build --release --workspace --bins)",
            dir.join(program).display()
        );
    }
    Ok(dir)
}

impl Supervisor<'_> {
    fn run(&mut self) -> Result<u8> {
        for member in self.plan.members() {
            let resume = self.plan.checkpoint.clone();
            self.start(member, resume)?;
        }
        self.announce();
        let mut code = 0;
        loop {
            match self.events.recv().context("every watcher is gone")? {
                Event::Interrupted => {
                    println!("\nstopping: the sim closes the episode and ends the run...");
                    self.interrupt_sims();
                }
                Event::UpdatesDone => {
                    self.updates_done = true;
                    println!(
                        "the critic has done its {} updates: the sims close their episodes and end the run...",
                        self.plan.updates.unwrap_or_default()
                    );
                    self.interrupt_sims();
                }
                Event::Exited(member, status) => {
                    self.running.remove(&member);
                    self.exits.insert(member, status);
                    if self.plan.restart_policy(member) == Restart::EndsTheRun {
                        break;
                    }
                    if !self.restart_if_due(member, status)? {
                        code = 1;
                    }
                }
            }
        }
        self.wind_down();
        Ok(self.report(code))
    }

    /// Starts one member with its log wired up and a thread that reports its exit.
    fn start(&mut self, member: Member, resume: Option<PathBuf>) -> Result<()> {
        let plan = self.plan;
        let minutes_left = self
            .ends_at
            .map(|end| end.saturating_duration_since(Instant::now()).as_secs_f64() / 60.0);
        let program = self.bin_dir.join(Plan::program(member));
        let mut command = Command::new(&program);
        command
            .args(plan.args(member, resume.as_deref(), minutes_left))
            .stdin(Stdio::null());
        let log_path = plan.log_path(member);
        // Robots append (a restarted robot continues its log); the sim's log is its run's.
        let log = OpenOptions::new()
            .create(true)
            .append(!matches!(member, Member::Sim { .. }))
            .write(true)
            .truncate(matches!(member, Member::Sim { .. }))
            .open(&log_path)
            .with_context(|| format!("cannot open {}", log_path.display()))?;
        if member == Member::Critic {
            // The critic's progress and its end-of-run table go to the terminal and its log.
            command.stdout(Stdio::piped()).stderr(Stdio::piped());
        } else if member == Member::Mcap {
            // Its first line says its state subscriber exists (read below).
            command.stdout(Stdio::piped()).stderr(log.try_clone()?);
        } else {
            command.stdout(log.try_clone()?).stderr(log.try_clone()?);
        }
        die_with_the_launcher(&mut command);
        let mut child = command
            .spawn()
            .with_context(|| format!("cannot start {}", program.display()))?;
        if let Some(stdout) = child.stdout.take_if(|_| member == Member::Mcap) {
            // The recorder must see the first tick: nothing else starts before it is ready.
            let mut stdout = BufReader::new(stdout);
            let mut line = String::new();
            stdout
                .read_line(&mut line)
                .context("reading the MCAP recorder's first line")?;
            if line.trim() != MCAP_READY_LINE {
                let _ = child.wait();
                anyhow::bail!(
                    "the MCAP recorder did not start: {}",
                    tail(&plan.log_path(member), 3).trim()
                );
            }
            let log = log.try_clone()?;
            self.tees.push(std::thread::spawn(move || {
                tee_lines(stdout, std::io::sink(), log, None)
            }));
        }
        if let Some(stdout) = child.stdout.take() {
            let log = log.try_clone()?;
            // The critic says so when its --updates are done.
            let watch = (member == Member::Critic).then(|| self.sender.clone());
            self.tees.push(std::thread::spawn(move || {
                tee_lines(stdout, std::io::stdout(), log, watch)
            }));
        }
        if let Some(stderr) = child.stderr.take() {
            self.tees.push(std::thread::spawn(move || {
                tee_lines(stderr, std::io::stderr(), log, None)
            }));
        }
        let quick_deaths = self.starts.get(&member).map_or(0, |(_, deaths)| *deaths);
        self.starts.insert(member, (Instant::now(), quick_deaths));
        self.running.insert(member, child.id());
        let exits = self.sender.clone();
        std::thread::spawn(move || {
            if let Ok(status) = child.wait() {
                let _ = exits.send(Event::Exited(member, status));
            }
        });
        Ok(())
    }

    /// The run's first lines: its id (tests and scripts read it), where results go, and how to
    /// attach the external robots.
    fn announce(&self) {
        let primary = self.plan.primary();
        let started = primary.n - primary.external.len() - primary.remote.len() - primary.ros2.len();
        println!(
            "run {}: sim, {started} agents and the critic started; results in {} (logs in {}/logs)",
            primary.identity.run_id,
            primary.run_dir.display(),
            primary.run_dir.display()
        );
        if let (Mode::Eval, Some(model)) = (self.plan.mode, &self.plan.checkpoint) {
            println!("learned robots drive with {}", model.display());
        }
        if !primary.external.is_empty() {
            let list: Vec<String> = primary.external.iter().map(usize::to_string).collect();
            println!(
                "external robots {}: the sim waits {} s for them to greet. Attach each one with",
                list.join(","),
                self.plan.config.ticks.startup_timeout_s
            );
            for index in &primary.external {
                println!(
                    "  python3 -m formation_swarm robot {} {index}        # the baseline in Python (pip install ./python)",
                    primary.run_dir.display()
                );
            }
            println!(
                "or from your code: formation_swarm.run_robot(\"{}\", INDEX, policy)  (run.json in {} has the rest)",
                primary.run_dir.display(),
                primary.run_dir.display()
            );
        }
        if !primary.ros2.is_empty() {
            let link = &self.plan.ros2;
            let list: Vec<String> = primary.ros2.iter().map(usize::to_string).collect();
            let (how, endpoint) = match &link.endpoint {
                crate::plan::Ros2Endpoint::Listen(e) => ("listening at", e),
                crate::plan::Ros2Endpoint::Connect(e) => ("dialling the router at", e),
            };
            println!(
                "ROS 2 robots {}: topics /{}/robot_<i>/{{odom,observation,cmd_vel}} and /clock on domain {}, rmw_zenoh's wire format, {how} {endpoint}; the sim waits {} s for each robot's node. Drive one with",
                list.join(","),
                link.namespace.trim_matches('/'),
                link.domain,
                self.plan.config.ticks.startup_timeout_s
            );
            for index in &primary.ros2 {
                println!(
                    "  python3 -m formation_swarm ros2-node {index} --endpoint {endpoint} --namespace {} --domain {}",
                    link.namespace.trim_matches('/'),
                    link.domain
                );
            }
            println!("or any ROS 2 node over rmw_zenoh_cpp (docs/ROS2.md)");
        }
        for host in &primary.remote {
            println!(
                "robot {} runs as if on another computer: its own iceoryx2 (run {}), joined over Zenoh at {}; its logs in {}/logs",
                host.robot,
                host.identity.run_id,
                self.plan.bridge_endpoint.as_deref().unwrap_or("-"),
                host.run_dir.display()
            );
        }
        for (k, swarm) in self.plan.swarms.iter().enumerate().skip(1) {
            println!(
                "extra swarm {k}: {} robots and their sim, run {}; results in {}",
                swarm.n,
                swarm.identity.run_id,
                swarm.run_dir.display()
            );
        }
    }

    /// Applies the member's restart policy after an exit; false when the run must stop.
    fn restart_if_due(&mut self, member: Member, status: ExitStatus) -> Result<bool> {
        let policy = self.plan.restart_policy(member);
        let critic_done = member == Member::Critic && self.updates_done;
        if status.success() || policy == Restart::Never || critic_done {
            // A clean exit, a member not to be restarted, or a critic whose updates are done.
            return Ok(true);
        }
        let name = self.plan.name(member);
        // A member that dies within seconds of each start (a bad binary, a broken checkpoint, a
        // port it cannot bind) is not restarted forever.
        let (started, quick_deaths) = self.starts.get(&member).copied().unwrap_or((Instant::now(), 0));
        let quick_deaths = if started.elapsed() < QUICK_DEATH {
            quick_deaths + 1
        } else {
            0
        };
        self.starts.insert(member, (started, quick_deaths));
        if quick_deaths >= QUICK_DEATHS_TO_GIVE_UP {
            eprintln!(
                "run_swarm.sh: {name} died at start three times in a row (see {}); stopping the run",
                self.plan.log_path(member).display()
            );
            self.interrupt_sims();
            return Ok(false);
        }
        if policy == Restart::OnFailureResuming {
            // Train: resume from the run's last checkpoint, else from where the run started.
            let last = self.plan.primary().run_dir.join("checkpoint.safetensors");
            let resume = match self.plan.mode {
                Mode::Train if last.is_file() => Some(last),
                Mode::Train => self.plan.checkpoint.clone(),
                Mode::Eval => None,
            };
            match &resume {
                Some(path) => println!("{name} died ({status}); restarting it from {}", path.display()),
                None => println!("{name} died ({status}); restarting it"),
            }
            self.start(member, resume)?;
        } else {
            println!("{name} died ({status}); restarting it");
            self.start(member, None)?;
        }
        Ok(true)
    }

    /// Ctrl-C to every sim: each closes its episode and tells its processes the run ended.
    fn interrupt_sims(&self) {
        for (member, pid) in &self.running {
            if matches!(member, Member::Sim { .. }) {
                signal(*pid, libc::SIGINT);
            }
        }
    }

    /// After the primary sim's end: extra sims get a moment and then Ctrl-C; every member gets
    /// [`WIND_DOWN`] to end on the end-of-run message, and a training critic up to
    /// [`CRITIC_WIND_DOWN`] more to score and save its last checkpoint.
    fn wind_down(&mut self) {
        let extra_sims: Vec<u32> = self
            .running
            .iter()
            .filter(|(member, _)| matches!(member, Member::Sim { .. }))
            .map(|(_, pid)| *pid)
            .collect();
        if !extra_sims.is_empty() {
            self.wait_for_exits(Instant::now() + EXTRA_SIM_GRACE, |m| !matches!(m, Member::Sim { .. }));
            self.interrupt_sims();
        }
        self.wait_for_exits(Instant::now() + WIND_DOWN, |_| false);
        if self.plan.mode == Mode::Train && self.running.contains_key(&Member::Critic) {
            println!(
                "waiting for the critic to score and save its last checkpoint (up to {} s)...",
                CRITIC_WIND_DOWN.as_secs()
            );
            self.wait_for_exits(Instant::now() + CRITIC_WIND_DOWN, |member| member != Member::Critic);
        }
    }

    /// Collects exits until `deadline`, or until only members `ignore` accepts are running.
    fn wait_for_exits(&mut self, deadline: Instant, ignore: impl Fn(Member) -> bool) {
        while self.running.keys().any(|&member| !ignore(member)) {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.events.recv_timeout(left) {
                Ok(Event::Exited(member, status)) => {
                    self.running.remove(&member);
                    self.exits.insert(member, status);
                }
                Ok(Event::Interrupted | Event::UpdatesDone) => {}
                Err(RecvTimeoutError::Timeout | RecvTimeoutError::Disconnected) => return,
            }
        }
    }

    /// Stops whatever still runs, naming it: SIGTERM, a moment, then SIGKILL.
    fn stop_all(&mut self) {
        if self.running.is_empty() {
            return;
        }
        let mut names: Vec<String> = self.running.keys().map(|&member| self.plan.name(member)).collect();
        names.sort();
        eprintln!(
            "run_swarm.sh: still running at the end of the run: {}; stopping them",
            names.join(", ")
        );
        for pid in self.running.values() {
            signal(*pid, libc::SIGTERM);
        }
        self.wait_for_exits(Instant::now() + Duration::from_millis(500), |_| false);
        for pid in self.running.values() {
            signal(*pid, libc::SIGKILL);
        }
        self.wait_for_exits(Instant::now() + Duration::from_secs(5), |_| false);
    }

    /// Prints what went wrong, if anything; returns the exit code.
    fn report(&self, code: u8) -> u8 {
        let primary = self.plan.primary();
        let sim_status = self.exits.get(&Member::Sim { swarm: 0 });
        let mut code = code;
        if let Some(status) = sim_status.filter(|s| !s.success()) {
            eprintln!("run_swarm.sh: the sim exited with {status}:");
            eprint!("{}", tail(&self.plan.log_path(Member::Sim { swarm: 0 }), 5));
            code = code.max(exit_code(status));
        }
        for index in (0..primary.n).filter(|i| !primary.external.contains(i)) {
            let log = tail(&self.plan.log_path(Member::Robot { swarm: 0, index }), 3);
            if log.contains("error") {
                eprint!("agent {index} reported:\n{log}");
            }
        }
        if let Some(status) = self.exits.get(&Member::Critic).filter(|s| !s.success()) {
            eprintln!("run_swarm.sh: the critic exited with {status}");
            if code == 0 {
                code = exit_code(status);
            }
        }
        code
    }
}

/// The last `lines` lines of a log file.
fn tail(path: &std::path::Path, lines: usize) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let all: Vec<&str> = text.lines().collect();
    let mut out = all[all.len().saturating_sub(lines)..].join("\n");
    if !out.is_empty() {
        out.push('\n');
    }
    out
}

/// A process's exit as a launcher exit code (a signal counts as 128 + its number).
fn exit_code(status: &ExitStatus) -> u8 {
    use std::os::unix::process::ExitStatusExt;
    let code = status.code().or_else(|| status.signal().map(|s| 128 + s)).unwrap_or(1);
    u8::try_from(code).unwrap_or(1).max(1)
}

/// Copies a child's lines to one of the launcher's outputs and to the child's log; with
/// `updates_done`, reports the critic's `UPDATE_BUDGET_SPENT` line on it.
fn tee_lines(from: impl std::io::Read, mut to: impl Write, mut log: File, updates_done: Option<Sender<Event>>) {
    let mut reader = BufReader::new(from);
    let mut line = Vec::new();
    while reader.read_until(b'\n', &mut line).is_ok_and(|n| n > 0) {
        let _ = to.write_all(&line);
        let _ = log.write_all(&line);
        if let Some(events) = &updates_done
            && String::from_utf8_lossy(&line).trim_end().ends_with(UPDATE_BUDGET_SPENT)
        {
            let _ = events.send(Event::UpdatesDone);
        }
        line.clear();
    }
}

/// Sends `signal` to a member.
fn signal(pid: u32, signal: i32) {
    // SAFETY: kill(2) on a child this launcher started and has not yet seen exit.
    unsafe { libc::kill(pid as libc::pid_t, signal) };
}

/// Each member runs in its own process group, so a terminal's Ctrl-C reaches only the
/// launcher (which asks the sim to end the run in order), and dies with the launcher however
/// the launcher ends (a watchdog's SIGKILL included), so no member outlives its run.
fn die_with_the_launcher(command: &mut Command) {
    let launcher = std::process::id() as libc::pid_t;
    command.process_group(0);
    // SAFETY: only async-signal-safe calls (prctl, getppid, _exit) between fork and exec.
    unsafe {
        command.pre_exec(move || {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            // The launcher died before the prctl: do not start an orphan.
            if libc::getppid() != launcher {
                libc::_exit(1);
            }
            Ok(())
        });
    }
}
