//! The agent's system-call policy: an allow-list modelled on Docker's default seccomp profile, compiled to BPF by
//! rust-vmm's `seccompiler` and installed by `sandbox-net` ([`crate::sandbox_net`]) just before it starts the agent.
//!
//! What an unlisted call gets is `EPERM`. Left out on purpose, each a channel between rollouts or a kernel surface no
//! agent needs: the keyrings (`add_key`, `keyctl`, `request_key`: a key stored by one rollout could be read by the
//! next), `io_uring_*`, `perf_event_open`, `bpf`, `userfaultfd`, `ptrace`, `process_vm_readv`/`writev`, `kcmp`,
//! `pidfd_getfd`, every namespace and mount call (`unshare`, `setns`, `mount`, `umount2`, `pivot_root`, `chroot`,
//! `fsopen`/`fsmount`/`fspick`/`open_tree`/`move_mount`/`mount_setattr`), `open_by_handle_at`, module, kexec, swap,
//! reboot, clock-setting, `acct`, `quotactl`, `syslog`, `personality` beyond the harmless flags, `sethostname`,
//! `setdomainname`, `iopl`/`ioperm`, `vhangup`, `lookup_dcookie`. `clone` is allowed without any `CLONE_NEW*` flag;
//! `clone3`, whose flags live in memory a filter cannot read, answers `ENOSYS` (a second, stacked filter), so the C
//! library falls back to `clone`. `socket` is allowed except for `AF_VSOCK` (a channel to the host's hypervisor).
//! A call of another ABI (i386 through `int 0x80`) kills the process: the architecture check `seccompiler` emits;
//! x32 numbers are not on the list.
use std::collections::BTreeMap;

use seccompiler::{BpfProgram, SeccompAction, SeccompCmpArgLen, SeccompCmpOp, SeccompCondition, SeccompFilter, SeccompRule, TargetArch};

/// Every CLONE_NEW* flag (NEWTIME, NEWNS, NEWCGROUP, NEWUTS, NEWIPC, NEWUSER, NEWPID, NEWNET).
const CLONE_NEW_ANY: u64 = 0x7e02_0080;
const AF_VSOCK: u64 = 40;
/// Calls the `libc` crate has no constant for yet (numbers from the kernel's syscall tables).
#[cfg(target_arch = "x86_64")]
const SYS_IO_PGETEVENTS: i64 = 333;
#[cfg(not(target_arch = "x86_64"))]
const SYS_IO_PGETEVENTS: i64 = 292;
const SYS_CACHESTAT: i64 = 451;

/// The calls any agent may make (Docker's default profile's unconditional list, less what the module docs name).
const ALLOWED: &[i64] = &[
    libc::SYS_accept, libc::SYS_accept4, libc::SYS_bind, libc::SYS_brk, libc::SYS_capget, libc::SYS_capset,
    libc::SYS_chdir, libc::SYS_clock_getres, libc::SYS_clock_gettime, libc::SYS_clock_nanosleep, libc::SYS_close,
    libc::SYS_close_range, libc::SYS_connect, libc::SYS_copy_file_range, libc::SYS_dup, libc::SYS_dup3,
    libc::SYS_epoll_create1, libc::SYS_epoll_ctl, libc::SYS_epoll_pwait, libc::SYS_epoll_pwait2, libc::SYS_eventfd2,
    libc::SYS_execve, libc::SYS_execveat, libc::SYS_exit, libc::SYS_exit_group, libc::SYS_faccessat,
    libc::SYS_faccessat2, libc::SYS_fadvise64, libc::SYS_fallocate, libc::SYS_fchdir, libc::SYS_fchmod,
    libc::SYS_fchmodat, libc::SYS_fchown, libc::SYS_fchownat, libc::SYS_fcntl, libc::SYS_fdatasync,
    libc::SYS_fgetxattr, libc::SYS_flistxattr, libc::SYS_flock, libc::SYS_fremovexattr, libc::SYS_fsetxattr,
    libc::SYS_fstat, libc::SYS_fstatfs, libc::SYS_fsync, libc::SYS_ftruncate, libc::SYS_futex, libc::SYS_futex_waitv,
    libc::SYS_get_mempolicy, libc::SYS_get_robust_list, libc::SYS_getcpu, libc::SYS_getcwd, libc::SYS_getdents64,
    libc::SYS_getegid, libc::SYS_geteuid, libc::SYS_getgid, libc::SYS_getgroups, libc::SYS_getitimer,
    libc::SYS_getpeername, libc::SYS_getpgid, libc::SYS_getpid, libc::SYS_getppid, libc::SYS_getpriority,
    libc::SYS_getrandom, libc::SYS_getresgid, libc::SYS_getresuid, libc::SYS_getrlimit, libc::SYS_getrusage,
    libc::SYS_getsid, libc::SYS_getsockname, libc::SYS_getsockopt, libc::SYS_gettid, libc::SYS_gettimeofday,
    libc::SYS_getuid, libc::SYS_getxattr, libc::SYS_inotify_add_watch, libc::SYS_inotify_init1,
    libc::SYS_inotify_rm_watch, libc::SYS_io_cancel, libc::SYS_io_destroy, libc::SYS_io_getevents,
    SYS_IO_PGETEVENTS, libc::SYS_io_setup, libc::SYS_io_submit, libc::SYS_ioctl, libc::SYS_ioprio_get,
    libc::SYS_ioprio_set, libc::SYS_kill, libc::SYS_landlock_add_rule, libc::SYS_landlock_create_ruleset,
    libc::SYS_landlock_restrict_self, libc::SYS_lgetxattr, libc::SYS_linkat, libc::SYS_listen, libc::SYS_listxattr,
    libc::SYS_llistxattr, libc::SYS_lremovexattr, libc::SYS_lseek, libc::SYS_lsetxattr, libc::SYS_madvise,
    libc::SYS_mbind, libc::SYS_membarrier, libc::SYS_memfd_create, libc::SYS_mincore, libc::SYS_mkdirat,
    libc::SYS_mknodat, libc::SYS_mlock, libc::SYS_mlock2, libc::SYS_mlockall, libc::SYS_mmap, libc::SYS_mprotect,
    libc::SYS_mq_getsetattr, libc::SYS_mq_notify, libc::SYS_mq_open, libc::SYS_mq_timedreceive,
    libc::SYS_mq_timedsend, libc::SYS_mq_unlink, libc::SYS_mremap, libc::SYS_msgctl, libc::SYS_msgget,
    libc::SYS_msgrcv, libc::SYS_msgsnd, libc::SYS_msync, libc::SYS_munlock, libc::SYS_munlockall, libc::SYS_munmap,
    libc::SYS_name_to_handle_at, libc::SYS_nanosleep, libc::SYS_newfstatat, libc::SYS_openat, libc::SYS_openat2,
    libc::SYS_pidfd_open, libc::SYS_pidfd_send_signal, libc::SYS_pipe2, libc::SYS_pkey_alloc, libc::SYS_pkey_free,
    libc::SYS_pkey_mprotect, libc::SYS_ppoll, libc::SYS_prctl, libc::SYS_pread64, libc::SYS_preadv,
    libc::SYS_preadv2, libc::SYS_prlimit64, libc::SYS_process_mrelease, libc::SYS_pselect6, libc::SYS_pwrite64,
    libc::SYS_pwritev, libc::SYS_pwritev2, libc::SYS_read, libc::SYS_readahead, libc::SYS_readlinkat,
    libc::SYS_readv, libc::SYS_recvfrom, libc::SYS_recvmmsg, libc::SYS_recvmsg, libc::SYS_remap_file_pages,
    libc::SYS_removexattr, libc::SYS_renameat, libc::SYS_renameat2, libc::SYS_restart_syscall, libc::SYS_rseq,
    libc::SYS_rt_sigaction, libc::SYS_rt_sigpending, libc::SYS_rt_sigprocmask, libc::SYS_rt_sigqueueinfo,
    libc::SYS_rt_sigreturn, libc::SYS_rt_sigsuspend, libc::SYS_rt_sigtimedwait, libc::SYS_rt_tgsigqueueinfo,
    libc::SYS_sched_get_priority_max, libc::SYS_sched_get_priority_min, libc::SYS_sched_getaffinity,
    libc::SYS_sched_getattr, libc::SYS_sched_getparam, libc::SYS_sched_getscheduler, libc::SYS_sched_rr_get_interval,
    libc::SYS_sched_setaffinity, libc::SYS_sched_setattr, libc::SYS_sched_setparam, libc::SYS_sched_setscheduler,
    libc::SYS_sched_yield, libc::SYS_seccomp, libc::SYS_semctl, libc::SYS_semget, libc::SYS_semop,
    libc::SYS_semtimedop, libc::SYS_sendfile, libc::SYS_sendmmsg, libc::SYS_sendmsg, libc::SYS_sendto,
    libc::SYS_set_mempolicy, libc::SYS_set_robust_list, libc::SYS_set_tid_address, libc::SYS_setfsgid,
    libc::SYS_setfsuid, libc::SYS_setgid, libc::SYS_setgroups, libc::SYS_setitimer, libc::SYS_setpgid,
    libc::SYS_setpriority, libc::SYS_setregid, libc::SYS_setresgid, libc::SYS_setresuid, libc::SYS_setreuid,
    libc::SYS_setrlimit, libc::SYS_setsid, libc::SYS_setsockopt, libc::SYS_setuid, libc::SYS_setxattr,
    libc::SYS_shmat, libc::SYS_shmctl, libc::SYS_shmdt, libc::SYS_shmget, libc::SYS_shutdown, libc::SYS_sigaltstack,
    libc::SYS_signalfd4, libc::SYS_socketpair, libc::SYS_splice, libc::SYS_statfs, libc::SYS_statx,
    libc::SYS_symlinkat, libc::SYS_sync, libc::SYS_sync_file_range, libc::SYS_syncfs, libc::SYS_sysinfo,
    libc::SYS_tee, libc::SYS_tgkill, libc::SYS_timer_create, libc::SYS_timer_delete, libc::SYS_timer_getoverrun,
    libc::SYS_timer_gettime, libc::SYS_timer_settime, libc::SYS_timerfd_create, libc::SYS_timerfd_gettime,
    libc::SYS_timerfd_settime, libc::SYS_times, libc::SYS_tkill, libc::SYS_truncate, libc::SYS_umask,
    libc::SYS_uname, libc::SYS_unlinkat, libc::SYS_utimensat, libc::SYS_vmsplice, libc::SYS_wait4, libc::SYS_waitid,
    libc::SYS_write, libc::SYS_writev, libc::SYS_fanotify_mark, libc::SYS_fchmodat2, SYS_CACHESTAT,
];

/// The x86-64 calls that newer architectures replaced by their `*at`/`2` forms.
#[cfg(target_arch = "x86_64")]
const ALLOWED_ARCH: &[i64] = &[
    libc::SYS_access, libc::SYS_alarm, libc::SYS_arch_prctl, libc::SYS_chmod, libc::SYS_chown, libc::SYS_creat,
    libc::SYS_dup2, libc::SYS_epoll_create, libc::SYS_epoll_wait, libc::SYS_eventfd, libc::SYS_fork,
    libc::SYS_futimesat, libc::SYS_getdents, libc::SYS_getpgrp, libc::SYS_inotify_init, libc::SYS_lchown,
    libc::SYS_link, libc::SYS_lstat, libc::SYS_mkdir, libc::SYS_mknod, libc::SYS_open, libc::SYS_pause,
    libc::SYS_pipe, libc::SYS_poll, libc::SYS_readlink, libc::SYS_rename, libc::SYS_rmdir, libc::SYS_select,
    libc::SYS_signalfd, libc::SYS_stat, libc::SYS_symlink, libc::SYS_time, libc::SYS_unlink, libc::SYS_utime,
    libc::SYS_utimes, libc::SYS_vfork, libc::SYS_set_thread_area, libc::SYS_get_thread_area, libc::SYS_modify_ldt,
];
#[cfg(not(target_arch = "x86_64"))]
const ALLOWED_ARCH: &[i64] = &[];

/// `personality` values Docker allows: the default domain, `UNAME26`, `ADDR_NO_RANDOMIZE` (what `setarch -R` and
/// debuggers ask for) and the query (0xffffffff).
const PERSONALITIES: [u64; 5] = [0x0, 0x8, 0x20000, 0x20008, 0xffff_ffff];

#[derive(Debug, thiserror::Error)]
#[error("the agent's seccomp policy: {0}")]
pub struct PolicyError(String);

fn arch() -> Result<TargetArch, PolicyError> {
    std::env::consts::ARCH.try_into().map_err(|e| PolicyError(format!("{e:?}")))
}

fn cond(arg: u8, len: SeccompCmpArgLen, op: SeccompCmpOp, value: u64) -> Result<SeccompCondition, PolicyError> {
    SeccompCondition::new(arg, len, op, value).map_err(|e| PolicyError(e.to_string()))
}

fn rule(conditions: Vec<SeccompCondition>) -> Result<SeccompRule, PolicyError> {
    SeccompRule::new(conditions).map_err(|e| PolicyError(e.to_string()))
}

/// The two programs [`install`] stacks: the allow-list, then `clone3` → ENOSYS.
pub fn programs() -> Result<[BpfProgram; 2], PolicyError> {
    let mut rules: BTreeMap<i64, Vec<SeccompRule>> = ALLOWED.iter().chain(ALLOWED_ARCH).map(|n| (*n, Vec::new())).collect();
    // clone without any CLONE_NEW* flag (threads, fork); clone3 passes this filter and meets the next one.
    rules.insert(
        libc::SYS_clone,
        vec![rule(vec![cond(0, SeccompCmpArgLen::Qword, SeccompCmpOp::MaskedEq(CLONE_NEW_ANY), 0)?])?],
    );
    rules.insert(libc::SYS_clone3, Vec::new());
    rules.insert(libc::SYS_socket, vec![rule(vec![cond(0, SeccompCmpArgLen::Dword, SeccompCmpOp::Ne, AF_VSOCK)?])?]);
    rules.insert(
        libc::SYS_personality,
        PERSONALITIES.iter().map(|p| rule(vec![cond(0, SeccompCmpArgLen::Dword, SeccompCmpOp::Eq, *p)?])).collect::<Result<_, _>>()?,
    );
    let allow = SeccompFilter::new(rules, SeccompAction::Errno(libc::EPERM as u32), SeccompAction::Allow, arch()?)
        .map_err(|e| PolicyError(e.to_string()))?;
    let clone3 = SeccompFilter::new(
        [(libc::SYS_clone3, Vec::new())].into_iter().collect(),
        SeccompAction::Allow,
        SeccompAction::Errno(libc::ENOSYS as u32),
        arch()?,
    )
    .map_err(|e| PolicyError(e.to_string()))?;
    let compile = |f: SeccompFilter| BpfProgram::try_from(f).map_err(|e| PolicyError(e.to_string()));
    Ok([compile(allow)?, compile(clone3)?])
}

/// Sets no_new_privs and installs the policy on the calling thread (and what it starts from now on).
pub fn install() -> Result<(), PolicyError> {
    for p in programs()? {
        seccompiler::apply_filter(&p).map_err(|e| PolicyError(e.to_string()))?;
    }
    Ok(())
}

/// For the harness manifest: the policy in words and numbers.
pub fn describe() -> serde_json::Value {
    serde_json::json!({
        "kind": "allow-list (Docker's default profile, less keyrings, io_uring, perf, bpf, userfaultfd, ptrace, namespaces and mounts)",
        "compiled_by": "seccompiler 0.5",
        "allowed_calls": ALLOWED.len() + ALLOWED_ARCH.len() + 4,
        "default": "EPERM",
        "conditional": {"clone": "no CLONE_NEW* flag", "clone3": "ENOSYS (falls back to clone)", "socket": "not AF_VSOCK",
            "personality": PERSONALITIES},
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Raw `syscall(2)` so the C library's fallbacks do not hide the filter's answer.
    fn errno_of(nr: i64, args: [libc::c_long; 4]) -> Option<i32> {
        // SAFETY: each call below is made with arguments the kernel rejects or that only affect this thread.
        let rc = unsafe { libc::syscall(nr, args[0], args[1], args[2], args[3]) };
        (rc < 0).then(|| std::io::Error::last_os_error().raw_os_error().unwrap_or(0))
    }

    /// The calls the issue names (and the rest of the kernel surface left out) fail with EPERM under the policy,
    /// on a thread of this test process; threads, processes, files and sockets still work.
    #[test]
    fn the_policy_refuses_keyrings_io_uring_perf_bpf_userfaultfd_ptrace_and_namespaces() {
        std::thread::spawn(|| {
            install().unwrap();
            let status = std::fs::read_to_string("/proc/thread-self/status").unwrap();
            assert!(status.lines().any(|l| l.starts_with("Seccomp:") && l.ends_with('2')), "{status}");
            let refused: &[(&str, i64, [libc::c_long; 4])] = &[
                ("add_key", libc::SYS_add_key, [0; 4]),
                ("keyctl", libc::SYS_keyctl, [0; 4]),
                ("request_key", libc::SYS_request_key, [0; 4]),
                ("io_uring_setup", libc::SYS_io_uring_setup, [1, 0, 0, 0]),
                ("io_uring_enter", libc::SYS_io_uring_enter, [0; 4]),
                ("perf_event_open", libc::SYS_perf_event_open, [0; 4]),
                ("bpf", libc::SYS_bpf, [0; 4]),
                ("userfaultfd", libc::SYS_userfaultfd, [0; 4]),
                ("ptrace", libc::SYS_ptrace, [libc::PTRACE_ATTACH as libc::c_long, 1, 0, 0]),
                ("process_vm_readv", libc::SYS_process_vm_readv, [1, 0, 0, 0]),
                ("unshare", libc::SYS_unshare, [libc::CLONE_NEWUSER as libc::c_long, 0, 0, 0]),
                ("setns", libc::SYS_setns, [-1, 0, 0, 0]),
                ("mount", libc::SYS_mount, [0; 4]),
                ("umount2", libc::SYS_umount2, [0; 4]),
                ("pivot_root", libc::SYS_pivot_root, [0; 4]),
                ("chroot", libc::SYS_chroot, [0; 4]),
                ("fsopen", libc::SYS_fsopen, [0; 4]),
                ("open_tree", libc::SYS_open_tree, [0; 4]),
                ("open_by_handle_at", libc::SYS_open_by_handle_at, [0; 4]),
                ("init_module", libc::SYS_init_module, [0; 4]),
                ("kexec_load", libc::SYS_kexec_load, [0; 4]),
                ("reboot", libc::SYS_reboot, [0; 4]),
                ("swapon", libc::SYS_swapon, [0; 4]),
                ("settimeofday", libc::SYS_settimeofday, [0; 4]),
                ("clock_settime", libc::SYS_clock_settime, [0; 4]),
                ("acct", libc::SYS_acct, [0; 4]),
                ("syslog", libc::SYS_syslog, [0; 4]),
                ("sethostname", libc::SYS_sethostname, [0; 4]),
                ("kcmp", libc::SYS_kcmp, [0; 4]),
                ("pidfd_getfd", libc::SYS_pidfd_getfd, [0; 4]),
                ("personality(READ_IMPLIES_EXEC)", libc::SYS_personality, [0x0040_0000, 0, 0, 0]),
                ("clone(CLONE_NEWNET)", libc::SYS_clone, [libc::CLONE_NEWNET as libc::c_long, 0, 0, 0]),
                ("socket(AF_VSOCK)", libc::SYS_socket, [AF_VSOCK as libc::c_long, libc::SOCK_STREAM as libc::c_long, 0, 0]),
            ];
            let wrong: Vec<String> = refused
                .iter()
                .filter_map(|(name, nr, args)| {
                    let e = errno_of(*nr, *args);
                    (e != Some(libc::EPERM)).then(|| format!("{name}: {e:?}"))
                })
                .collect();
            assert!(wrong.is_empty(), "not refused with EPERM: {wrong:?}");
            assert_eq!(errno_of(libc::SYS_clone3, [0; 4]), Some(libc::ENOSYS), "clone3 → ENOSYS");
            // What agents do all day still works.
            assert_eq!(std::thread::spawn(|| 7).join().unwrap(), 7, "threads start (clone3 falls back to clone)");
            assert!(std::process::Command::new("true").status().unwrap().success(), "processes start");
            let out = std::process::Command::new("python3").args(["-c", "import socket,os,tempfile; s=socket.socket(); s.close(); print(os.getpid() > 0)"]).output().unwrap();
            assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "True", "{out:?}");
            let out = std::process::Command::new("sh").args(["-c", "echo x > /dev/null && ls / >/dev/null && echo ok"]).output().unwrap();
            assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), "ok", "{out:?}");
            assert_eq!(errno_of(libc::SYS_personality, [0xffff_ffff, 0, 0, 0]), None, "the personality query is allowed");
            let out = std::process::Command::new("unshare").args(["-Ur", "true"]).output().unwrap();
            assert!(!out.status.success(), "unshare(1) -Ur must fail: {out:?}");
        })
        .join()
        .unwrap();
    }

    #[test]
    fn the_policy_compiles_for_this_architecture() {
        let [allow, clone3] = programs().unwrap();
        assert!(allow.len() > 200 && clone3.len() < 20, "{} {}", allow.len(), clone3.len());
        assert!(u16::try_from(allow.len()).is_ok(), "a classic BPF program has at most 4096 instructions");
    }
}
