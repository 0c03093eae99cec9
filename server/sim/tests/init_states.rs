//! The pure-Rust `.pruned_init` reader returns exactly the rows the reference stack loaded.
mod common;

use common::*;
use libero_sim::{InitStates, SimError};

#[test]
fn stock_init_files_match_the_rows_recorded_in_the_golden_files() {
    let paths = assets();
    for name in golden_names() {
        let g = load_golden(&name);
        let file = paths.libero_root.join(&g.init_file_relpath);
        let states = InitStates::read(&file).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(states.len(), 50, "{name}: pruned init files hold 50 states");
        assert_eq!(states.row_len(), g.init_state.len(), "{name}: row length 1 + nq + nv");
        let row = states.get(g.init_state_index).expect("row");
        assert!(row.iter().zip(&g.init_state).all(|(a, b)| a.to_bits() == b.to_bits()), "{name}: row differs");
        assert!(matches!(states.get(50), Err(SimError::Input(_))));
    }
}

#[test]
fn non_pickle_files_are_input_errors() {
    let dir = std::env::temp_dir().join(format!("libero-sim-init-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let not_zip = dir.join("x.pruned_init");
    std::fs::write(&not_zip, b"not a zip").unwrap();
    assert!(matches!(InitStates::read(&not_zip), Err(SimError::Input(_))));
    assert!(matches!(InitStates::read(&dir.join("missing.pruned_init")), Err(SimError::Input(_))));
    std::fs::remove_dir_all(&dir).ok();
}
