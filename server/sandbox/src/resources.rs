//! What one rollout's agent may take of the machine, and who it is: every process, byte of memory, share of CPU
//! and byte of disk it uses is capped per rollout, and each rollout runs as a host uid of its own.
//!
//! - **Processes, memory, CPU**: a cgroup per rollout (v2 where the host has the unified hierarchy with the
//!   controllers, else v1's `pids`, `memory` and `cpu` hierarchies), made below the runner's own cgroup. bubblewrap
//!   is moved into it before it runs (a pre-exec hook writes `0` to `cgroup.procs`), so everything the agent starts
//!   is inside. The memory cap includes what the agent writes to its in-memory disk; past it the kernel's OOM
//!   killer picks a process of that cgroup alone: the agent's tree, never the server.
//! - **Disk**: the workspace, the session home, the sandbox's `/tmp` and the CLI's stdout/stderr all live on one
//!   size-capped tmpfs per rollout, mounted by the (root) runner at `<workspace root>/<rollout id>`: a write past the
//!   cap fails with `ENOSPC` inside the sandbox, and nothing the agent writes reaches the filesystem of the server's
//!   records. When the rollout ends its logs (scrubbed, bounded) are kept in the rollout directory and the rest goes
//!   with the mount: nothing a rollout left is there for the next.
//! - **Identity**: as root, each rollout's agent is a uid (and gid) of its own, drawn from `--agent-uids` and held
//!   by a lock file for as long as the rollout runs, never one that any process of the host runs as.
//!
//! Where a cap cannot be enforced (an ordinary user's runner cannot mount; no writable cgroup), `run` and `worker`
//! refuse to start and say why, unless `--unconfined-resources` says to run without these caps.
use std::ffi::CString;
use std::io::Write as _;
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use serde_json::{Value, json};

/// Default caps of one rollout's agent.
pub const DEFAULT_MAX_PROCESSES: u64 = 1024;
pub const DEFAULT_MEMORY_BYTES: u64 = 4 << 30;
pub const DEFAULT_DISK_BYTES: u64 = 2 << 30;
/// The default range of host uids (and gids) agents run as when the runner is root: far from Debian's users
/// (1000–59999), its dynamic users (61184–65519) and `nobody`, inside the 32-bit id space every filesystem here takes.
pub const DEFAULT_AGENT_UIDS: (u32, u32) = (3_000_000, 3_065_535);
/// cgroup v2's `cpu.weight` of an agent (the default is 100) and v1's `cpu.shares` (default 1024): under contention
/// the server's simulation and rendering come first.
const CPU_WEIGHT: u32 = 50;
const CPU_SHARES: u32 = 512;
const CPU_PERIOD_US: u64 = 100_000;

/// `run`'s and `worker`'s flags for the caps.
#[derive(clap::Args, Debug, Clone)]
pub struct ResourceArgs {
    /// Processes and threads one rollout's agent may have at once (its whole tree).
    #[arg(long, default_value_t = DEFAULT_MAX_PROCESSES, value_parser = clap::value_parser!(u64).range(16..=1_000_000))]
    pub agent_max_processes: u64,
    /// Memory of one rollout's agent, its in-memory disk included (`4GiB`, `512MiB`, bytes).
    #[arg(long, default_value = "4GiB", value_parser = parse_bytes)]
    pub agent_memory: u64,
    /// CPUs one rollout's agent may keep busy (a quota; default: every CPU of the machine). Its weight is half the
    /// server's either way.
    #[arg(long, value_parser = parse_cpus)]
    pub agent_cpus: Option<f64>,
    /// Disk of one rollout's agent: workspace, session home, /tmp and its stdout/stderr together (`2GiB`).
    #[arg(long, default_value = "2GiB", value_parser = parse_bytes)]
    pub agent_disk: u64,
    /// Host uids (and gids) agents run as when the runner is root, one per rollout: `START-END`.
    #[arg(long, value_parser = parse_uid_range, default_value = "3000000-3065535")]
    pub agent_uids: (u32, u32),
    /// Run agents without per-rollout caps on processes, memory, CPU and disk where this machine cannot enforce
    /// them (an ordinary user's runner, no writable cgroup): without it such a runner refuses to start.
    #[arg(long)]
    pub unconfined_resources: bool,
}

impl Default for ResourceArgs {
    fn default() -> Self {
        Self {
            agent_max_processes: DEFAULT_MAX_PROCESSES,
            agent_memory: DEFAULT_MEMORY_BYTES,
            agent_cpus: None,
            agent_disk: DEFAULT_DISK_BYTES,
            agent_uids: DEFAULT_AGENT_UIDS,
            unconfined_resources: false,
        }
    }
}

/// `2GiB`, `512MiB`, `100M`, `4096`: bytes.
pub fn parse_bytes(s: &str) -> Result<u64, String> {
    let t = s.trim();
    let split = t.find(|c: char| !c.is_ascii_digit()).unwrap_or(t.len());
    let (num, unit) = t.split_at(split);
    let n: u64 = num.parse().map_err(|_| format!("{s:?}: expected a size like 2GiB, 512MiB or a number of bytes"))?;
    let mult: u64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1,
        "k" | "kib" | "kb" => 1 << 10,
        "m" | "mib" | "mb" => 1 << 20,
        "g" | "gib" | "gb" => 1 << 30,
        "t" | "tib" | "tb" => 1 << 40,
        u => return Err(format!("{s:?}: unknown unit {u:?} (B, KiB, MiB, GiB, TiB)")),
    };
    let bytes = n.checked_mul(mult).ok_or_else(|| format!("{s:?}: too large"))?;
    if !(16 << 20..=1 << 50).contains(&bytes) {
        return Err(format!("{s:?}: between 16MiB and 1PiB"));
    }
    Ok(bytes)
}

fn parse_cpus(s: &str) -> Result<f64, String> {
    let v: f64 = s.trim().parse().map_err(|_| format!("{s:?}: expected a number of CPUs like 1 or 0.5"))?;
    if !(0.05..=4096.0).contains(&v) {
        return Err(format!("{s:?}: between 0.05 and 4096"));
    }
    Ok(v)
}

fn parse_uid_range(s: &str) -> Result<(u32, u32), String> {
    let (a, b) = s.split_once('-').ok_or_else(|| format!("{s:?}: expected START-END"))?;
    let a: u32 = a.trim().parse().map_err(|e| format!("{a:?}: {e}"))?;
    let b: u32 = b.trim().parse().map_err(|e| format!("{b:?}: {e}"))?;
    if a == 0 || b < a || b == u32::MAX {
        return Err(format!("{s:?}: a range of non-root ids, START ≤ END"));
    }
    Ok((a, b))
}

/// The caps in force for a run, as detected once: how each is enforced on this machine.
#[derive(Debug, Clone)]
pub struct Resources {
    pub max_processes: u64,
    pub memory_bytes: u64,
    pub cpus: Option<f64>,
    pub disk_bytes: u64,
    /// Where the per-rollout cgroups are made.
    cgroups: Cgroups,
    /// Agent uid range (root runners).
    pub agent_uids: Option<(u32, u32)>,
    /// Where the uid locks live.
    lock_dir: PathBuf,
}

#[derive(Debug, Clone)]
enum Cgroups {
    /// The unified hierarchy: one directory under which each rollout gets `libero-<id>`.
    V2(PathBuf),
    /// v1: the runner's own directory in the `pids`, `memory` and `cpu` hierarchies.
    V1 { pids: PathBuf, memory: PathBuf, cpu: PathBuf },
}

impl Resources {
    /// The caps of `args`, or `None` with `--unconfined-resources` where they cannot be enforced. An error says
    /// what is missing and names the flag.
    pub fn detect(args: &ResourceArgs) -> anyhow::Result<Option<Self>> {
        match Self::try_detect(args) {
            Ok(r) => Ok(Some(r)),
            Err(e) if args.unconfined_resources => {
                eprintln!("warning: --unconfined-resources: agents run without per-rollout caps ({e:#})");
                Ok(None)
            }
            Err(e) => Err(e.context(
                "cannot cap each agent's processes, memory, CPU and disk on this machine; pass --unconfined-resources to \
                 run agents without these caps",
            )),
        }
    }

    fn try_detect(args: &ResourceArgs) -> anyhow::Result<Self> {
        // SAFETY: geteuid(2) has no preconditions.
        if unsafe { libc::geteuid() } != 0 {
            bail!("the runner is not root: it cannot mount each rollout's size-capped disk nor switch the agent to a uid of its own");
        }
        let cgroups = find_cgroups().context("no writable cgroup with the pids, memory and cpu controllers")?;
        let lock_dir = ["/run/libero-agent/uids", "/var/lock/libero-agent-uids"]
            .iter()
            .map(PathBuf::from)
            .find(|d| std::fs::create_dir_all(d).is_ok())
            .unwrap_or_else(|| std::env::temp_dir().join("libero-agent-uids"));
        std::fs::create_dir_all(&lock_dir).with_context(|| format!("cannot create {}", lock_dir.display()))?;
        let r = Self {
            max_processes: args.agent_max_processes,
            memory_bytes: args.agent_memory,
            cpus: args.agent_cpus,
            disk_bytes: args.agent_disk,
            cgroups,
            agent_uids: Some(args.agent_uids),
            lock_dir,
        };
        let swept = sweep_orphaned_disks();
        if swept > 0 {
            eprintln!("unmounted {swept} rollout disk(s) left mounted by a runner that is gone");
        }
        // A probe rollout: its cgroup made and removed, its disk mounted and unmounted.
        static PROBES: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = PROBES.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let probe = std::env::temp_dir().join(format!("libero-agent-probe-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&probe).with_context(|| format!("cannot create {}", probe.display()))?;
        let cage = r.for_rollout("probe", &probe).context("a probe rollout's cage").map(drop);
        let _ = std::fs::remove_dir(&probe);
        cage?;
        Ok(r)
    }

    /// For the harness manifest and `batch.json`: the caps and how they are enforced.
    pub fn describe(&self) -> Value {
        json!({
            "max_processes": self.max_processes,
            "memory_bytes": self.memory_bytes,
            "cpus": self.cpus,
            "cpu_weight": match self.cgroups { Cgroups::V2(_) => json!({"cpu.weight": CPU_WEIGHT}), Cgroups::V1 { .. } => json!({"cpu.shares": CPU_SHARES}) },
            "disk_bytes": self.disk_bytes,
            "enforced_by": match &self.cgroups {
                Cgroups::V2(p) => format!("cgroup v2 below {}; a size-capped tmpfs per rollout", p.display()),
                Cgroups::V1 { memory, .. } => format!("cgroup v1 (pids, memory, cpu) below {}; a size-capped tmpfs per rollout", memory.display()),
            },
            "agent_uids": self.agent_uids.map(|(a, b)| format!("{a}-{b}")),
        })
    }

    /// Makes one rollout's cage: its cgroup(s), its uid, and its disk mounted at `<workspace_root>/<rollout id>`.
    pub fn for_rollout(&self, rollout_id: &str, workspace_root: &Path) -> anyhow::Result<RolloutCage> {
        let name = format!("libero-{}", sanitize(rollout_id));
        let mut cage = RolloutCage { cgroups: Vec::new(), disk: None, ids: None, _uid_lock: None, v2: matches!(self.cgroups, Cgroups::V2(_)) };
        match &self.cgroups {
            Cgroups::V2(base) => {
                let dir = fresh_cgroup(base, &name)?;
                cage.cgroups.push(dir.clone());
                write_file(&dir.join("pids.max"), &self.max_processes.to_string())?;
                write_file(&dir.join("memory.max"), &self.memory_bytes.to_string())?;
                let _ = write_file(&dir.join("memory.swap.max"), "0");
                let _ = write_file(&dir.join("memory.oom.group"), "0");
                write_file(&dir.join("cpu.weight"), &CPU_WEIGHT.to_string())?;
                if let Some(c) = self.cpus {
                    write_file(&dir.join("cpu.max"), &format!("{} {CPU_PERIOD_US}", (c * CPU_PERIOD_US as f64).round() as u64))?;
                }
            }
            Cgroups::V1 { pids, memory, cpu } => {
                let p = fresh_cgroup(pids, &name)?;
                cage.cgroups.push(p.clone());
                write_file(&p.join("pids.max"), &self.max_processes.to_string())?;
                let m = fresh_cgroup(memory, &name)?;
                cage.cgroups.push(m.clone());
                write_file(&m.join("memory.limit_in_bytes"), &self.memory_bytes.to_string())?;
                // With swap accounting, memory+swap gets the same cap: nothing is swapped out to escape it.
                let _ = write_file(&m.join("memory.memsw.limit_in_bytes"), &self.memory_bytes.to_string());
                let c = fresh_cgroup(cpu, &name)?;
                cage.cgroups.push(c.clone());
                write_file(&c.join("cpu.shares"), &CPU_SHARES.to_string())?;
                if let Some(n) = self.cpus {
                    write_file(&c.join("cpu.cfs_period_us"), &CPU_PERIOD_US.to_string())?;
                    write_file(&c.join("cpu.cfs_quota_us"), &((n * CPU_PERIOD_US as f64).round() as u64).to_string())?;
                }
            }
        }
        if let Some(range) = self.agent_uids {
            let (uid, lock) = claim_uid(range, &self.lock_dir)?;
            cage.ids = Some((uid, uid));
            cage._uid_lock = Some(lock);
        }
        let mount_point = workspace_root.join(sanitize(rollout_id));
        std::fs::create_dir(&mount_point).with_context(|| format!("cannot create {}", mount_point.display()))?;
        let disk = Disk::mount(&mount_point, self.disk_bytes).inspect_err(|_| {
            let _ = std::fs::remove_dir(&mount_point);
        })?;
        for sub in ["workspace", "home", "tmp", "logs"] {
            std::fs::create_dir(mount_point.join(sub)).with_context(|| format!("cannot create {sub} on the rollout's disk"))?;
        }
        set_mode(&mount_point.join("logs"), 0o700)?;
        set_mode(&mount_point.join("home"), 0o700)?;
        set_mode(&mount_point.join("tmp"), 0o1777)?;
        // Who holds this disk: a runner killed with SIGKILL leaves it mounted, and the next one unmounts it.
        std::fs::write(mount_point.join(CAGE_MARKER), format!("{}\n", std::process::id())).context("cannot mark the rollout's disk")?;
        cage.disk = Some(disk);
        Ok(cage)
    }
}

/// One rollout's cgroups, uid and disk; dropping it kills whatever is left in the cgroups, removes them, and
/// unmounts the disk.
#[derive(Debug)]
pub struct RolloutCage {
    cgroups: Vec<PathBuf>,
    disk: Option<Disk>,
    /// The agent's uid and gid.
    pub ids: Option<(u32, u32)>,
    _uid_lock: Option<std::fs::File>,
    v2: bool,
}

impl RolloutCage {
    fn on_disk(&self, sub: &str) -> Option<PathBuf> {
        self.disk.as_ref().map(|d| d.mount_point.join(sub))
    }
    /// The workspace on the rollout's disk.
    pub fn workspace(&self) -> Option<PathBuf> {
        self.on_disk("workspace")
    }
    pub fn home(&self) -> Option<PathBuf> {
        self.on_disk("home")
    }
    /// Shown as the sandbox's `/tmp`.
    pub fn tmp(&self) -> Option<PathBuf> {
        self.on_disk("tmp")
    }
    /// Where the CLI's stdout and stderr are written (the runner's, not visible inside the sandbox).
    pub fn logs(&self) -> Option<PathBuf> {
        self.on_disk("logs")
    }

    /// A pre-exec hook that moves the new process into the rollout's cgroups: `0` written to each `cgroup.procs`
    /// (async-signal-safe: only open(2), write(2), close(2) on paths made beforehand).
    pub fn attach_hook(&self) -> impl FnMut() -> std::io::Result<()> + Send + Sync + 'static {
        let paths: Vec<CString> = self
            .cgroups
            .iter()
            .filter_map(|d| CString::new(d.join("cgroup.procs").into_os_string().into_encoded_bytes()).ok())
            .collect();
        move || {
            for p in &paths {
                // SAFETY: open/write/close on a NUL-terminated path owned by the closure; no allocation here.
                unsafe {
                    let fd = libc::open(p.as_ptr(), libc::O_WRONLY | libc::O_CLOEXEC);
                    if fd < 0 {
                        return Err(std::io::Error::last_os_error());
                    }
                    let rc = libc::write(fd, b"0".as_ptr().cast(), 1);
                    let err = std::io::Error::last_os_error();
                    libc::close(fd);
                    if rc != 1 {
                        return Err(err);
                    }
                }
            }
            Ok(())
        }
    }

    /// What the agent used and met, for the harness manifest: peak memory, OOM kills, refused forks, disk used.
    pub fn usage(&self) -> Value {
        let read = |p: PathBuf| std::fs::read_to_string(p).ok().map(|s| s.trim().to_owned());
        let num = |p: PathBuf| read(p).and_then(|s| s.parse::<u64>().ok());
        let field = |p: PathBuf, key: &str| {
            read(p).and_then(|s| s.lines().find_map(|l| l.strip_prefix(key).and_then(|v| v.trim().parse::<u64>().ok())))
        };
        let mut v = json!({});
        for dir in &self.cgroups {
            if self.v2 {
                v["memory_peak_bytes"] = json!(num(dir.join("memory.peak")));
                v["oom_kills"] = json!(field(dir.join("memory.events"), "oom_kill "));
                v["processes_peak"] = json!(num(dir.join("pids.peak")));
                v["forks_refused"] = json!(field(dir.join("pids.events"), "max "));
            } else if dir.join("pids.max").exists() {
                v["processes_peak"] = json!(num(dir.join("pids.peak")));
                v["forks_refused"] = json!(field(dir.join("pids.events"), "max "));
            } else if dir.join("memory.limit_in_bytes").exists() {
                v["memory_peak_bytes"] = json!(num(dir.join("memory.max_usage_in_bytes")));
                v["oom_kills"] = json!(field(dir.join("memory.oom_control"), "oom_kill "));
                v["memory_limit_hits"] = json!(num(dir.join("memory.failcnt")));
            }
        }
        if let Some(d) = &self.disk {
            v["disk_used_bytes"] = json!(d.used_bytes());
        }
        v
    }

    /// Ends every process left in the rollout's cgroups (what escaped the process group: `setsid`, daemons).
    pub fn kill_all(&self) {
        for dir in &self.cgroups {
            if self.v2 && write_file(&dir.join("cgroup.kill"), "1").is_ok() {
                continue;
            }
            for _ in 0..20 {
                let pids: Vec<i32> = std::fs::read_to_string(dir.join("cgroup.procs"))
                    .unwrap_or_default()
                    .lines()
                    .filter_map(|l| l.trim().parse().ok())
                    .collect();
                if pids.is_empty() {
                    break;
                }
                for pid in pids {
                    // SAFETY: kill(2) of a process in the agent's own cgroup.
                    unsafe { libc::kill(pid, libc::SIGKILL) };
                }
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
        }
    }
}

impl Drop for RolloutCage {
    fn drop(&mut self) {
        self.kill_all();
        for dir in &self.cgroups {
            // The kernel removes a cgroup once its last process is gone; a few tries while they exit.
            for _ in 0..100 {
                match std::fs::remove_dir(dir) {
                    Ok(()) => break,
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => break,
                    Err(_) => std::thread::sleep(std::time::Duration::from_millis(20)),
                }
            }
        }
        // The disk unmounts when `disk` drops (after the cgroups: nothing of the agent holds it open then).
        self.disk.take();
    }
}

/// A size-capped tmpfs at `mount_point` (root-owned, 0755, nosuid, nodev), unmounted and its directory removed
/// when dropped.
#[derive(Debug)]
struct Disk {
    mount_point: PathBuf,
}

impl Disk {
    fn mount(mount_point: &Path, bytes: u64) -> anyhow::Result<Self> {
        // One inode per 4 KiB of the cap: a flood of empty files meets the cap too.
        let inodes = (bytes / 4096).clamp(16_384, 4 << 20);
        let options = CString::new(format!("size={bytes},nr_inodes={inodes},mode=0755,uid=0,gid=0"))?;
        let target = CString::new(mount_point.as_os_str().as_encoded_bytes())?;
        let fstype = CString::new("tmpfs")?;
        // SAFETY: mount(2) with NUL-terminated strings that outlive the call.
        let rc = unsafe {
            libc::mount(fstype.as_ptr(), target.as_ptr(), fstype.as_ptr(), libc::MS_NOSUID | libc::MS_NODEV, options.as_ptr().cast())
        };
        if rc != 0 {
            bail!("cannot mount the rollout's disk (tmpfs of {bytes} bytes) at {}: {}", mount_point.display(), std::io::Error::last_os_error());
        }
        Ok(Self { mount_point: mount_point.to_path_buf() })
    }

    fn used_bytes(&self) -> Option<u64> {
        let p = CString::new(self.mount_point.as_os_str().as_encoded_bytes()).ok()?;
        let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
        // SAFETY: statvfs(2) into a zeroed struct of the right type.
        (unsafe { libc::statvfs(p.as_ptr(), &mut st) } == 0).then(|| (st.f_blocks - st.f_bfree) * st.f_frsize)
    }
}

impl Drop for Disk {
    fn drop(&mut self) {
        if let Ok(p) = CString::new(self.mount_point.as_os_str().as_encoded_bytes()) {
            // SAFETY: umount2(2) of the mount this value made. MNT_DETACH: an open descriptor left somewhere (a
            // reader of the logs) does not keep the mount point busy; the memory is freed once it closes.
            unsafe { libc::umount2(p.as_ptr(), libc::MNT_DETACH) };
        }
        let _ = std::fs::remove_dir(&self.mount_point);
    }
}

/// The file at the root of each rollout's disk naming the pid of the runner that holds it (the agent cannot
/// write there: the root is the runner's, 0755).
const CAGE_MARKER: &str = ".libero-cage";

/// Unmounts every rollout disk (a tmpfs with a [`CAGE_MARKER`] at its root) whose runner is no longer running;
/// returns how many. A live runner's disks, and anything not marked, are left alone.
pub fn sweep_orphaned_disks() -> usize {
    let mountinfo = std::fs::read_to_string("/proc/self/mountinfo").unwrap_or_default();
    let mut swept = 0;
    for line in mountinfo.lines() {
        let Some((left, right)) = line.split_once(" - ") else { continue };
        if right.split_whitespace().next() != Some("tmpfs") {
            continue;
        }
        // The mount point, with the kernel's octal escapes for space, tab, newline and backslash undone.
        let Some(raw) = left.split_whitespace().nth(4) else { continue };
        let point = PathBuf::from(raw.replace("\\040", " ").replace("\\011", "\t").replace("\\012", "\n").replace("\\134", "\\"));
        let Ok(marker) = std::fs::read_to_string(point.join(CAGE_MARKER)) else { continue };
        let Ok(pid) = marker.trim().parse::<i32>() else { continue };
        // SAFETY: kill(2) with signal 0 only asks whether the process exists.
        let alive = pid > 0 && (unsafe { libc::kill(pid, 0) } == 0 || std::io::Error::last_os_error().raw_os_error() == Some(libc::EPERM));
        if alive {
            continue;
        }
        drop(Disk { mount_point: point });
        swept += 1;
    }
    swept
}

/// A free uid of `range`: locked by an exclusive `flock` on `<lock_dir>/<uid>` (held by the returned file for the
/// rollout's life, by whatever runner or worker of this host holds it), and no process of the host runs as it.
fn claim_uid(range: (u32, u32), lock_dir: &Path) -> anyhow::Result<(u32, std::fs::File)> {
    let span = u64::from(range.1 - range.0) + 1;
    let busy = uids_in_use();
    for _ in 0..256 {
        let mut r = [0u8; 8];
        // SAFETY: getrandom(2) fills the buffer it is given.
        unsafe { libc::getrandom(r.as_mut_ptr().cast(), r.len(), 0) };
        let uid = range.0 + (u64::from_le_bytes(r) % span) as u32;
        if busy.contains(&uid) {
            continue;
        }
        let path = lock_dir.join(uid.to_string());
        let f = std::fs::OpenOptions::new().create(true).truncate(false).write(true).open(&path).with_context(|| format!("cannot open {}", path.display()))?;
        // SAFETY: flock(2) on a descriptor this function owns.
        if unsafe { libc::flock(f.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } == 0 {
            let mut f = f;
            let _ = f.set_len(0);
            let _ = writeln!(f, "{}", std::process::id());
            return Ok((uid, f));
        }
    }
    bail!("no free agent uid in {}-{} after 256 draws", range.0, range.1)
}

/// The real and effective uids of every process of the host.
fn uids_in_use() -> std::collections::HashSet<u32> {
    let mut out = std::collections::HashSet::new();
    for e in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
        if !e.file_name().to_string_lossy().bytes().all(|b| b.is_ascii_digit()) {
            continue;
        }
        if let Ok(s) = std::fs::read_to_string(e.path().join("status"))
            && let Some(line) = s.lines().find(|l| l.starts_with("Uid:"))
        {
            out.extend(line.split_whitespace().skip(1).filter_map(|w| w.parse::<u32>().ok()));
        }
    }
    out
}

/// Where this process's cgroups are, and which of them can hold the agents' (the unified hierarchy first).
fn find_cgroups() -> anyhow::Result<Cgroups> {
    let own = std::fs::read_to_string("/proc/self/cgroup").context("cannot read /proc/self/cgroup")?;
    let path_of = |controller: &str| {
        own.lines().find_map(|l| {
            let mut parts = l.splitn(3, ':');
            let (_, names, path) = (parts.next()?, parts.next()?, parts.next()?);
            names.split(',').any(|n| n == controller).then(|| path.trim_start_matches('/').to_owned())
        })
    };
    // v2: /sys/fs/cgroup is the unified hierarchy and offers the three controllers.
    let unified = Path::new("/sys/fs/cgroup");
    if let Ok(controllers) = std::fs::read_to_string(unified.join("cgroup.controllers"))
        && ["pids", "memory", "cpu"].iter().all(|c| controllers.split_whitespace().any(|x| x == *c))
    {
        let rel = own.lines().find_map(|l| l.strip_prefix("0::")).unwrap_or("/").trim_start_matches('/').to_owned();
        return v2_base(&unified.join(rel)).map(Cgroups::V2);
    }
    let v1 = |controller: &str| -> anyhow::Result<PathBuf> {
        let mount = [format!("/sys/fs/cgroup/{controller}"), "/sys/fs/cgroup/cpu,cpuacct".to_owned()]
            .into_iter()
            .map(PathBuf::from)
            .find(|m| m.join("cgroup.procs").exists() && (controller != "cpu" || m.join("cpu.shares").exists()))
            .with_context(|| format!("no cgroup v1 {controller} hierarchy under /sys/fs/cgroup"))?;
        let rel = path_of(controller).unwrap_or_default();
        let dir = if mount.join(&rel).is_dir() { mount.join(rel) } else { mount };
        let base = dir.join("libero-agent");
        std::fs::create_dir_all(&base).with_context(|| format!("cannot create {}", base.display()))?;
        Ok(base)
    };
    Ok(Cgroups::V1 { pids: v1("pids")?, memory: v1("memory")?, cpu: v1("cpu")? })
}

/// A v2 directory whose children can use the pids, memory and cpu controllers: `<own>/libero-agent`, with the
/// controllers enabled on the way. cgroup v2 lets no process live in a cgroup that hands controllers to its
/// children, so when the runner's own cgroup holds processes the runner first moves itself into a leaf
/// `<own>/libero-runner`.
fn v2_base(own: &Path) -> anyhow::Result<PathBuf> {
    let enable = |dir: &Path| write_file(&dir.join("cgroup.subtree_control"), "+pids +memory +cpu");
    if enable(own).is_err() {
        let leaf = own.join("libero-runner");
        std::fs::create_dir_all(&leaf).with_context(|| format!("cannot create {}", leaf.display()))?;
        let procs = std::fs::read_to_string(own.join("cgroup.procs")).unwrap_or_default();
        for pid in procs.lines().filter(|l| !l.trim().is_empty()) {
            // Another process of the runner's cgroup (the shell that started it) moves along: it is the runner's.
            let _ = write_file(&leaf.join("cgroup.procs"), pid.trim());
        }
        enable(own).with_context(|| format!("cannot enable the pids, memory and cpu controllers below {}", own.display()))?;
    }
    let base = own.join("libero-agent");
    std::fs::create_dir_all(&base).with_context(|| format!("cannot create {}", base.display()))?;
    enable(&base).with_context(|| format!("cannot enable the pids, memory and cpu controllers below {}", base.display()))?;
    Ok(base)
}

/// `<base>/<name>`, or `<base>/<name>-<n>` when a cgroup of that name is still being torn down.
fn fresh_cgroup(base: &Path, name: &str) -> anyhow::Result<PathBuf> {
    for n in 0..100 {
        let dir = if n == 0 { base.join(name) } else { base.join(format!("{name}-{n}")) };
        match std::fs::create_dir(&dir) {
            Ok(()) => return Ok(dir),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e).with_context(|| format!("cannot create the cgroup {}", dir.display())),
        }
    }
    bail!("cannot create a cgroup {name} below {}", base.display())
}

fn write_file(path: &Path, text: &str) -> anyhow::Result<()> {
    std::fs::write(path, text).with_context(|| format!("cannot write {text:?} to {}", path.display()))
}

fn set_mode(path: &Path, mode: u32) -> anyhow::Result<()> {
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode)).with_context(|| format!("cannot chmod {}", path.display()))
}

fn sanitize(id: &str) -> String {
    id.chars().map(|c| if c.is_ascii_alphanumeric() || "-_.".contains(c) { c } else { '_' }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_and_ranges_parse_with_units_and_bounds() {
        assert_eq!(parse_bytes("2GiB"), Ok(2 << 30));
        assert_eq!(parse_bytes("512MiB"), Ok(512 << 20));
        assert_eq!(parse_bytes("100M"), Ok(100 << 20));
        assert_eq!(parse_bytes("33554432"), Ok(32 << 20));
        assert!(parse_bytes("1KiB").is_err() && parse_bytes("-1").is_err() && parse_bytes("2 parsecs").is_err() && parse_bytes("99999999999TiB").is_err());
        assert_eq!(parse_uid_range("3000000-3065535"), Ok(DEFAULT_AGENT_UIDS));
        assert!(parse_uid_range("0-10").is_err() && parse_uid_range("10-5").is_err() && parse_uid_range("10").is_err());
        assert!(parse_cpus("0.5").is_ok() && parse_cpus("0").is_err() && parse_cpus("x").is_err());
    }

    /// A runner killed with SIGKILL leaves its rollout's disk mounted; the next one's start unmounts it, and leaves
    /// a live runner's disk alone.
    #[test]
    fn a_disk_left_by_a_runner_that_is_gone_is_unmounted_and_a_live_one_is_not() {
        if !root() {
            eprintln!("not root: the cage needs root");
            return;
        }
        let args = ResourceArgs { agent_disk: 16 << 20, ..Default::default() };
        let r = Resources::detect(&args).unwrap().unwrap();
        let dir = tempfile::tempdir().unwrap();
        let live = r.for_rollout("live", dir.path()).unwrap();
        let orphan = r.for_rollout("orphan", dir.path()).unwrap();
        let orphan_point = orphan.workspace().unwrap().parent().unwrap().to_path_buf();
        // A dead runner's pid: a child that has exited and been reaped.
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let dead = child.id();
        child.wait().unwrap();
        std::fs::write(orphan_point.join(CAGE_MARKER), format!("{dead}\n")).unwrap();
        let orphan_cgroups = orphan.cgroups.clone();
        std::mem::forget(orphan);
        let mounted = |p: &Path| std::fs::read_to_string("/proc/self/mountinfo").unwrap().contains(&format!(" {} ", p.display()));
        assert!(mounted(&orphan_point));
        assert!(sweep_orphaned_disks() >= 1);
        assert!(!mounted(&orphan_point), "the orphan's disk is unmounted");
        assert!(live.workspace().unwrap().is_dir(), "the live runner's disk stays");
        for c in orphan_cgroups {
            let _ = std::fs::remove_dir(c);
        }
    }

    fn root() -> bool {
        // SAFETY: geteuid(2) has no preconditions.
        unsafe { libc::geteuid() == 0 }
    }

    /// As root: a rollout's cage caps a fork flood, an allocation and a disk fill below their caps, each refused
    /// inside the cage while this (the server's) process goes on; the uid is one no other cage holds; dropping the
    /// cage leaves no cgroup and no mount behind.
    #[test]
    fn a_rollout_s_cage_refuses_forks_memory_and_disk_past_its_caps() {
        if !root() {
            eprintln!("not root: the cage needs root (run as root in `make test`)");
            return;
        }
        let args = ResourceArgs { agent_max_processes: 64, agent_memory: 256 << 20, agent_disk: 32 << 20, ..Default::default() };
        let r = Resources::detect(&args).unwrap().unwrap();
        let root_dir = tempfile::tempdir().unwrap();
        let cage = r.for_rollout("t1", root_dir.path()).unwrap();
        let other = r.for_rollout("t2", root_dir.path()).unwrap();
        assert_ne!(cage.ids, other.ids, "each rollout has its own uid");
        drop(other);
        let (uid, _) = cage.ids.unwrap();
        assert!((DEFAULT_AGENT_UIDS.0..=DEFAULT_AGENT_UIDS.1).contains(&uid));
        let ws = cage.workspace().unwrap();
        std::os::unix::fs::chown(&ws, Some(uid), Some(uid)).unwrap();
        let forks = "import os, signal, time\nkids = []\nfor i in range(100):\n    try:\n        pid = os.fork()\n    except OSError:\n        break\n    if pid == 0:\n        time.sleep(30)\n        os._exit(0)\n    kids.append(pid)\nprint('forks=%d' % len(kids), flush=True)\nfor k in kids:\n    os.kill(k, signal.SIGKILL)\n    os.waitpid(k, 0)";
        let script = format!(
            "cd {ws}; python3 -c \"$FORKS\"; \
             dd if=/dev/zero of=fill bs=1M count=64 2>&1; \
             python3 -c 'b = b\"x\" * (400 << 20); print(\"allocated\")'; echo py=$?",
            ws = ws.display()
        );
        let mut cmd = std::process::Command::new("setpriv");
        cmd.env("FORKS", forks).args(["--reuid", &uid.to_string(), "--regid", &uid.to_string(), "--clear-groups", "--", "sh", "-c", &script]);
        // SAFETY: the hook only makes async-signal-safe calls (see attach_hook).
        unsafe { std::os::unix::process::CommandExt::pre_exec(&mut cmd, cage.attach_hook()) };
        let out = cmd.output().unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
        let forks: u32 = text.lines().find_map(|l| l.strip_prefix("forks=")).and_then(|n| n.trim().parse().ok()).unwrap_or(999);
        assert!(forks < 64, "forks past the cap of 64: {text}");
        assert!(text.contains("No space left on device"), "the disk fill is refused inside: {text}");
        assert!(!text.contains("allocated"), "a 400 MiB allocation under a 256 MiB cap: {text}");
        let used = cage.usage();
        assert!(used["disk_used_bytes"].as_u64().is_some_and(|b| b <= 32 << 20), "{used}");
        assert!(used["oom_kills"].as_u64().is_some_and(|n| n >= 1) || used["memory_limit_hits"].as_u64().is_some_and(|n| n >= 1), "{used}");
        let mount = ws.parent().unwrap().to_path_buf();
        let cgroups = cage.cgroups.clone();
        drop(cage);
        assert!(!mount.exists(), "the rollout's disk is gone");
        assert!(cgroups.iter().all(|c| !c.exists()), "{cgroups:?}");
        assert!(!std::fs::read_to_string("/proc/self/mounts").unwrap().contains(&mount.display().to_string()));
    }
}
