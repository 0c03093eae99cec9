//! A throwaway PostgreSQL cluster for tests (Debian's `postgresql` package), shared by the store's unit tests and
//! the integration tests. As root the cluster runs as the `postgres` user (initdb refuses root).
#![allow(dead_code)]
use std::path::PathBuf;

/// A throwaway PostgreSQL cluster (Debian's `postgresql` package) on a free loopback port, removed on drop.
/// As root, the cluster runs as the `postgres` user (initdb refuses root).
pub struct TestPostgres {
    dir: tempfile::TempDir,
    bin: PathBuf,
    pub url: String,
}

impl TestPostgres {
    pub fn start() -> Self {
        let bin = std::fs::read_dir("/usr/lib/postgresql")
            .expect("PostgreSQL is missing: run `python3 scripts/setup.py --test` (Debian package postgresql)")
            .flatten()
            .map(|e| e.path().join("bin"))
            .filter(|b| b.join("initdb").is_file())
            .max()
            .expect("no /usr/lib/postgresql/<version>/bin/initdb");
        let dir = tempfile::tempdir().unwrap();
        let root = is_root();
        let data = dir.path().join("pg");
        std::fs::create_dir(&data).unwrap();
        if root {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o711)).unwrap();
            let ok = std::process::Command::new("chown").args(["postgres:postgres"]).arg(&data).status().unwrap();
            assert!(ok.success(), "chown postgres {}", data.display());
        }
        let out = as_owner(&bin.join("initdb")).args(["-A", "trust", "-U", "libero", "--no-sync", "-D"]).arg(&data).output().unwrap();
        assert!(out.status.success(), "initdb: {}", String::from_utf8_lossy(&out.stderr));
        let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
        let opts = format!("-p {port} -k {} -c listen_addresses=127.0.0.1 -c fsync=off", data.display());
        let out = as_owner(&bin.join("pg_ctl")).args(["-w", "-D"]).arg(&data).args(["-o", &opts, "-l"]).arg(data.join("log")).arg("start").output().unwrap();
        assert!(out.status.success(), "pg_ctl start: {}", String::from_utf8_lossy(&out.stderr));
        Self { dir, bin, url: format!("postgres://libero@127.0.0.1:{port}/postgres") }
    }
}

impl Drop for TestPostgres {
    fn drop(&mut self) {
        let data = self.dir.path().join("pg");
        let _ = as_owner(&self.bin.join("pg_ctl")).args(["-m", "immediate", "-D"]).arg(&data).arg("stop").output();
    }
}

fn is_root() -> bool {
    // SAFETY: geteuid has no preconditions.
    unsafe { libc::geteuid() == 0 }
}

/// `program` run as the cluster's owner: `postgres` when this process is root, else this user.
fn as_owner(program: &std::path::Path) -> std::process::Command {
    if is_root() {
        let mut c = std::process::Command::new("runuser");
        c.args(["-u", "postgres", "--"]).arg(program);
        c
    } else {
        std::process::Command::new(program)
    }
}
