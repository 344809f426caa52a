//! The learned method's travel-time stretch search (`gprflow_register::stretch`,
//! `Model::assess_best`) on the trained model and a pair of its fixtures: a query whose travel
//! times were stretched, as a pass over wetter soil would be, is found again at the factor that
//! undoes the stretch, and registered where the unstretched search refuses it.
//!
//! Needs ONNX Runtime's library, as tests/learned_parity.rs.

mod common;

use common::{ort_library, read_f32, repo_root};
use gprflow_register::SubmapView;
use gprflow_register::learned::{Features, Model};
use gprflow_register::stretch::{factors, stretch_rows};

const FIXTURES: &str = "stages/register/tests/fixtures/learned";

fn view(pixels: &[f32]) -> SubmapView<'_> {
    SubmapView {
        pixels,
        rows: 201,
        cols: 200,
        resolution_m: 0.015,
    }
}

fn committed_model() -> Model {
    let root = repo_root();
    Model::load(
        &root.join("stages/register/models/ground_encoding.onnx"),
        &root.join("stages/register/models/ground_encoding.head.json"),
        Some(&ort_library()),
    )
    .expect("the committed model")
}

/// A fixture case's reference and query submaps.
fn fixture_pair(name: &str) -> (Vec<f32>, Vec<f32>) {
    let dir = repo_root().join(FIXTURES);
    (
        read_f32(&dir.join(format!("{name}.reference.f32"))),
        read_f32(&dir.join(format!("{name}.query.f32"))),
    )
}

/// The query's features at each factor of the search.
fn search(model: &mut Model, query: &[f32], at: &[f64]) -> Vec<Features> {
    let mut stretched = Vec::new();
    at.iter()
        .map(|&f| {
            stretch_rows(&view(query), f, &mut stretched).expect("stretches");
            model.encode(&view(&stretched)).expect("encodes")
        })
        .collect()
}

#[test]
fn a_stretched_query_is_found_again_at_the_factor_that_undoes_it() {
    let mut model = committed_model();
    // two passes of one by_hand run over the same ground (held-out scenario), registered as
    // they are (manifest: target -0.934 m, mean peak 0.644, registered)
    let (reference, query) = fixture_pair("different_legs");
    let target_m = -0.933_918_880_828_944;
    let fr = model.encode(&view(&reference)).expect("encodes");

    // the query as a pass over slower ground would see it: every arrival 1 / 0.95 later
    let mut slower = Vec::new();
    stretch_rows(&view(&query), 0.95, &mut slower).expect("stretches");

    let unstretched = search(&mut model, &slower, &[1.0]);
    let (plain, refusal, _) = model.assess_best(&fr, &unstretched, 0.015).expect("assesses");
    assert!(
        refusal.is_some(),
        "unstretched the slower query should be refused: {:.3} m, share {:.3}, agreement {:.2}",
        plain.shift_m,
        plain.share_score,
        plain.agreement
    );

    let at = factors(0.02, 2).expect("factors");
    let queries = search(&mut model, &slower, &at);
    let (found, refusal, best) = model.assess_best(&fr, &queries, 0.015).expect("assesses");
    // 0.95 x 1.04 = 0.988: the factor that undoes the stretch (the two legs, minutes apart
    // on drying soil, match best at about 0.985 as they are)
    assert_eq!(at[best], 1.04, "chose {} (share {:.3})", at[best], found.share_score);
    assert_eq!(
        refusal, None,
        "share {:.3}, agreement {:.2}",
        found.share_score, found.agreement
    );
    assert!(
        found.share_score > plain.share_score + 0.05,
        "{} vs {}",
        found.share_score,
        plain.share_score
    );
    assert!(
        (found.shift_m - target_m).abs() < 0.05,
        "{:.3} m against the truth's {target_m:.3} m",
        found.shift_m
    );
    // each candidate decides on its own correlation: the chosen one is the highest share
    for (i, q) in queries.iter().enumerate() {
        let (m, _, _) = model
            .assess_best(&fr, std::slice::from_ref(q), 0.015)
            .expect("assesses");
        assert!(
            m.share_score <= found.share_score,
            "factor {}: {}",
            at[i],
            m.share_score
        );
    }
}

#[test]
fn two_runs_over_soil_of_other_moisture_register_only_with_the_search() {
    let mut model = committed_model();
    // two runs over the same ground of the held-out scenario, the soil's moisture different
    // (manifest: target -1.359 m, mean peak 0.376, refused, the head's shift -0.24 m)
    let (reference, query) = fixture_pair("different_runs");
    let target_m = -1.358_790_073_053_071_5;
    let fr = model.encode(&view(&reference)).expect("encodes");
    let unstretched = search(&mut model, &query, &[1.0]);
    let (plain, refusal, _) = model.assess_best(&fr, &unstretched, 0.015).expect("assesses");
    assert!(
        refusal.is_some(),
        "{:.3} m, share {:.3}",
        plain.shift_m,
        plain.share_score
    );
    // a search wide enough for a change of moisture between runs (the stage's default, 1 +-
    // 0.015, is chosen for passes minutes apart)
    let at = factors(0.03, 2).expect("factors");
    let queries = search(&mut model, &query, &at);
    let (found, refusal, best) = model.assess_best(&fr, &queries, 0.015).expect("assesses");
    assert_eq!(at[best], 1.06, "chose {} (share {:.3})", at[best], found.share_score);
    assert_eq!(
        refusal, None,
        "share {:.3}, agreement {:.2}",
        found.share_score, found.agreement
    );
    assert!(
        (found.shift_m - target_m).abs() < 0.05,
        "{:.3} m against the truth's {target_m:.3} m",
        found.shift_m
    );
}

#[test]
fn no_query_is_an_error_not_a_panic() {
    let root = repo_root();
    let mut model = Model::load(
        &root.join("stages/register/models/ground_encoding.onnx"),
        &root.join("stages/register/models/ground_encoding.head.json"),
        Some(&ort_library()),
    )
    .expect("the committed model");
    let reference = read_f32(&root.join(FIXTURES).join("different_legs.reference.f32"));
    let fr = model.encode(&view(&reference)).expect("encodes");
    assert!(model.assess_best(&fr, &[], 0.015).is_err());
}
