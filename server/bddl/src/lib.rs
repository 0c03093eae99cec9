//! LIBERO BDDL parser.
