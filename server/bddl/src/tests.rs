use super::*;

const MINIMAL: &str = "(define (problem LIBERO_Tabletop_Manipulation)
  (:domain robosuite)
  (:language Put the Bowl on the plate) ; a comment
  (:regions
    (bowl_region (:target main_table) (:ranges ((-0.1 -0.2 0.1 0.2))) (:yaw_rotation ((0 0) (3.141592653589793 pi))))
    (top_region (:target wooden_cabinet_1)))
  (:fixtures main_table - table wooden_cabinet_1 - wooden_cabinet)
  (:objects bowl_1 bowl_2 - akita_black_bowl plate_1 - plate)
  (:obj_of_interest bowl_1)
  (:init (On bowl_1 main_table_bowl_region) (Open wooden_cabinet_1_top_region))
  (:goal (And (On bowl_1 plate_1) (Or (Open wooden_cabinet_1_top_region) (Not (Close wooden_cabinet_1_top_region)))))
)";

#[test]
fn minimal_problem_fields_follow_libero_semantics() {
    let p = Problem::parse(MINIMAL).expect("parses");
    assert_eq!(p.problem_name, "libero_tabletop_manipulation");
    assert_eq!(p.language, "put the bowl on the plate");
    assert_eq!(p.regions.len(), 2);
    let r = &p.regions[0];
    assert_eq!(r.key, "main_table_bowl_region");
    assert_eq!(r.ranges, vec![[-0.1, -0.2, 0.1, 0.2]]);
    // last pair wins; `pi` is accepted like Python's eval
    assert_eq!(r.yaw_rotation, [std::f64::consts::PI, std::f64::consts::PI]);
    assert_eq!(r.rgba, [0.0, 0.0, 1.0, 0.0]);
    assert_eq!(p.regions[1].key, "wooden_cabinet_1_top_region");
    let names: Vec<_> = p.objects.iter().map(|i| (i.name.as_str(), i.category.as_str())).collect();
    assert_eq!(names, vec![("bowl_1", "akita_black_bowl"), ("bowl_2", "akita_black_bowl"), ("plate_1", "plate")]);
    assert_eq!(p.fixtures[1].category, "wooden_cabinet");
    assert_eq!(p.init[1].predicate, "open");
    assert_eq!(p.goal_atoms(), None, "or/not is not a pure conjunction");
    match p.goal.as_ref().unwrap() {
        Expr::And(items) => assert!(matches!(items[1], Expr::Or(_))),
        other => panic!("{other:?}"),
    }
}

#[test]
fn repeated_type_in_one_section_replaces_the_earlier_group_like_libero() {
    let p = Problem::parse("(define (problem x) (:objects a - bowl b - plate c - bowl d))").unwrap();
    let names: Vec<_> = p.objects.iter().map(|i| (i.name.as_str(), i.category.as_str())).collect();
    assert_eq!(names, vec![("c", "bowl"), ("b", "plate"), ("d", "object")]);
}

#[test]
fn unbalanced_parenthesis_reports_line_and_column() {
    let e = Problem::parse("(define (problem x)\n  (:objects a - bowl\n").unwrap_err();
    assert_eq!((e.line, e.column), (2, 3), "{e}");
    assert!(e.to_string().contains("never closed"), "{e}");
    let e = Problem::parse("(define (problem x)))").unwrap_err();
    assert_eq!((e.line, e.column), (1, 21), "{e}");
}

#[test]
fn bad_range_rectangle_is_rejected_with_position() {
    let e = Problem::parse("(define (problem x)\n (:regions (r (:target main_table)\n (:ranges ((0 0 1))))))").unwrap_err();
    assert_eq!(e.line, 3, "{e}");
    assert!(e.message.contains("4 numbers"), "{e}");
    let e = Problem::parse("(define (problem x) (:regions (r (:target t) (:ranges ((0 0 1 zz))))))").unwrap_err();
    assert!(e.message.contains("`zz` is not a number"), "{e}");
}

#[test]
fn region_without_target_and_unknown_attribute_are_errors() {
    let e = Problem::parse("(define (problem x) (:regions (r (:ranges ((0 0 1 1))))))").unwrap_err();
    assert!(e.message.contains("no (:target"), "{e}");
    let e = Problem::parse("(define (problem x) (:regions (r (:target t) (:colour red))))").unwrap_err();
    assert!(e.message.contains("unknown region attribute `:colour`"), "{e}");
}

#[test]
fn wrong_domain_missing_define_and_extra_toplevel_are_errors() {
    assert!(Problem::parse("(define (problem x) (:domain igibson))").unwrap_err().message.contains("robosuite"));
    assert!(Problem::parse("(problem x)").unwrap_err().message.contains("(define"));
    assert!(Problem::parse("(define (problem x)) (foo)").unwrap_err().message.contains("more than one top-level"));
    assert!(Problem::parse("").is_err());
    assert!(Problem::parse("(define (:domain robosuite))").unwrap_err().message.contains("problem NAME"));
}

#[test]
fn file_errors_name_the_file() {
    let dir = std::env::temp_dir().join(format!("bddl_test_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let f = dir.join("bad.bddl");
    std::fs::write(&f, "(define (problem x)\n(:init (on a b)").unwrap();
    let e = Problem::from_file(&f).unwrap_err();
    assert!(e.to_string().starts_with(&format!("{}:2:1:", f.display())), "{e}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn language_from_filename_matches_libero() {
    assert_eq!(
        language_from_filename("KITCHEN_SCENE3_turn_on_the_stove_and_put_the_moka_pot_on_it"),
        "turn on the stove and put the moka pot on it"
    );
    assert_eq!(language_from_filename("pick_up_the_ketchup_and_place_it_in_the_basket.bddl"), "pick up the ketchup and place it in the basket");
}
