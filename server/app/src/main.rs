fn main() -> anyhow::Result<()> {
    let xml = std::env::args().nth(1).unwrap_or_default();
    let m = libero_sim::mujoco_rs::prelude::MjModel::from_xml(&xml)?;
    println!("nq={} nv={}", m.ffi().nq, m.ffi().nv);
    Ok(())
}
