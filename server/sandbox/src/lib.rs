//! The agent's boundary, in one crate: everything that stands between a benchmark agent (a coding CLI) and the
//! machine it runs on. Kept apart from the runner's batches, harnesses and reports so that the security-critical
//! code is in one place, small enough to review whole, with its own tests, and changes to it show as changes to
//! this crate alone (docs/threat_model.md names its files as the proofs).
//!
//! - [`sandbox`]: the bubblewrap argv (what the agent sees of the file system, which namespaces it gets);
//! - [`sandbox_net`]: `libero-agent sandbox-net`, the sandbox's first process: the loopback relays, the drop to the
//!   agent's user, and the [`seccomp`] allow-list;
//! - [`agent_net`]: what an agent can reach, and the runner's side of it ([`netgate`]: the model-API gateway, its
//!   proxy, relays and token records);
//! - [`resources`]: per-rollout caps (cgroups, a size-capped disk, a uid of its own);
//! - [`logs`]: the agent's stdout and stderr, bounded and scrubbed of secrets;
//! - [`toolbox`]: the agent's read-only Python.
//!
//! No simulator, no HTTP server, no batches: the runner (`libero-runner`) builds on it.
pub mod agent_net;
pub mod host_paths;
pub mod logs;
pub mod netgate;
pub mod resources;
pub mod sandbox;
pub mod sandbox_net;
pub mod seccomp;
pub mod toolbox;
