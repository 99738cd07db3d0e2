//! Model configs: parsing, recognition of the known models, validation against a signature.

use super::*;

fn tensor(name: &str, shape: &[i64]) -> TensorInfo {
    TensorInfo {
        name: name.into(),
        shape: Some(shape.to_vec()),
        is_f32: true,
    }
}

fn pydnet_sig() -> ModelSignature {
    ModelSignature {
        inputs: vec![tensor("image", &[1, 3, 448, 640])],
        outputs: vec![
            tensor("depth_half", &[1, 1, 448, 640]),
            tensor("depth_quarter", &[1, 1, 448, 640]),
            tensor("depth_eighth", &[1, 1, 448, 640]),
        ],
    }
}

#[test]
fn dense_config_parses_toml_and_json_with_defaults() {
    let toml = r#"
        name = "m"
        input = "x"
        input_width = 256
        input_height = 256
        mean = [0.485, 0.456, 0.406]
        std = [0.229, 0.224, 0.225]
        output = "y"
        output_kind = "inverse_depth"
    "#;
    let c = ModelConfig::from_toml(toml).expect("valid toml");
    assert_eq!(c.layout, Layout::Nchw);
    assert_eq!(c.resize, ResizeMode::Stretch);
    assert_eq!(c.intra_threads, 2);
    assert!((c.scale - 1.0 / 255.0).abs() < 1e-9);
    assert_eq!(c.std, IMAGENET_STD);
    let json = serde_json::to_string(&c).expect("serialise");
    assert_eq!(ModelConfig::from_json(&json).expect("valid json"), c);
}

#[test]
fn dense_config_rejects_unknown_fields_and_bad_values() {
    let base = "name='m'\ninput='x'\ninput_width=8\ninput_height=8\noutput='y'\n\
                output_kind='depth'\n";
    assert!(ModelConfig::from_toml(base).is_ok());
    assert!(ModelConfig::from_toml(&format!("{base}stdd=[1,1,1]\n")).is_err());
    assert!(ModelConfig::from_toml(&format!("{base}std=[1,0,1]\n")).is_err());
    assert!(ModelConfig::from_toml(&format!("{base}intra_threads=0\n")).is_err());
    assert!(ModelConfig::from_toml(&format!("{base}multiple_of=3\n")).is_err());
    assert!(ModelConfig::from_toml(&base.replace("'depth'", "'dispariti'")).is_err());
    let disparity = base.replace("'depth'", "'disparity'");
    let c = ModelConfig::from_toml(&disparity).expect("disparity is an output kind");
    assert!(!c.metric, "relative unless said otherwise");
    assert!(ModelConfig::from_toml(&format!("{disparity}metric=true\n")).is_err());
    let metric = ModelConfig::from_toml(&format!("{base}metric=true\n")).expect("metric");
    assert!(metric.metric && metric.output_kind.grows_with_distance());
}

#[test]
fn dense_recognises_pydnet_by_sha_and_signature() {
    let (c, how) = recognise(&pydnet_sig(), PYDNET_PP_SHA256, "x.onnx").expect("known");
    assert_eq!(how, Recognition::Sha256);
    assert_eq!(
        (c.input.as_str(), c.output.as_str()),
        ("image", "depth_half")
    );
    assert_eq!((c.input_width, c.input_height), (640, 448));
    assert_eq!(c.output_kind, OutputKind::Depth);
    c.validate(&pydnet_sig()).expect("its own config fits");
    let (_, how) = recognise(&pydnet_sig(), "00", "x.onnx").expect("known by shape");
    assert_eq!(how, Recognition::Signature);
}

#[test]
fn dense_recognises_midas_depth_anything_and_dpt() {
    let midas = ModelSignature {
        inputs: vec![tensor("0", &[1, 3, 256, 256])],
        outputs: vec![tensor("797", &[1, 256, 256])],
    };
    let (c, _) = recognise(&midas, "00", "m.onnx").expect("midas");
    assert_eq!(c.output, "797");
    assert_eq!(c.mean, IMAGENET_MEAN);
    c.validate(&midas).expect("fits");
    let (c, how) = recognise(&midas, MIDAS_V21_SMALL_RELEASE_SHA256, "m.onnx").expect("midas");
    assert_eq!(how, Recognition::Sha256);
    assert_eq!(c.mean, [0.0; 3], "the release graph normalises internally");

    let da = ModelSignature {
        inputs: vec![tensor("pixel_values", &[-1, 3, -1, -1])],
        outputs: vec![tensor("predicted_depth", &[-1, -1, -1])],
    };
    let (c, _) = recognise(&da, "00", "model.onnx").expect("depth anything");
    assert_eq!(
        (c.resize, c.multiple_of),
        (ResizeMode::KeepAspect, Some(14))
    );
    c.validate(&da).expect("fits");

    let dpt = ModelSignature {
        inputs: vec![tensor("input", &[1, 3, 384, 384])],
        outputs: vec![tensor("output", &[1, 384, 384])],
    };
    assert!(
        recognise(&dpt, "00", "model.onnx").is_none(),
        "384 alone is ambiguous"
    );
    let (c, _) = recognise(&dpt, "00", "dpt_hybrid_384.onnx").expect("dpt");
    assert_eq!(c.std, [0.5; 3]);
}

fn fastdepth_sig(side: i64) -> ModelSignature {
    ModelSignature {
        inputs: vec![tensor("image", &[1, 3, side, side])],
        outputs: vec![tensor("depth", &[1, 1, side, side])],
    }
}

#[test]
fn dense_recognises_fastdepth_as_metric_depth() {
    for (sig, sha, how) in [
        (
            fastdepth_sig(224),
            FASTDEPTH_NYU_SHA256,
            Recognition::Sha256,
        ),
        (fastdepth_sig(224), "00", Recognition::Signature),
        (fastdepth_sig(-1), "00", Recognition::Signature),
    ] {
        let (c, found) = recognise(&sig, sha, "fastdepth.onnx").expect("fastdepth");
        assert_eq!(found, how);
        assert_eq!(c.name, "fastdepth_nyu_224");
        assert_eq!((c.input_width, c.input_height), (224, 224));
        assert_eq!(
            (c.resize, c.mean, c.std),
            (ResizeMode::Stretch, [0.0; 3], [1.0; 3])
        );
        assert_eq!(c.output_kind, OutputKind::Depth);
        assert!(c.metric);
        c.validate(&sig).expect("its own config fits");
    }
}

#[test]
fn dense_relative_models_are_never_metric() {
    let da_fixed = ModelSignature {
        inputs: vec![tensor("image", &[1, 3, 224, 224])],
        outputs: vec![tensor("depth", &[1, 224, 224])],
    };
    let (c, _) = recognise(&da_fixed, "00", "model.onnx").expect("depth anything");
    assert_eq!(c.name, "depth_anything_v2", "rank-3 output: not FastDepth");
    let midas = ModelSignature {
        inputs: vec![tensor("0", &[1, 3, 256, 256])],
        outputs: vec![tensor("797", &[1, 256, 256])],
    };
    let relative = [
        recognise(&pydnet_sig(), PYDNET_PP_SHA256, "").expect("pydnet"),
        recognise(&pydnet_sig(), "00", "").expect("pydnet"),
        recognise(&midas, "00", "").expect("midas"),
        recognise(&midas, MIDAS_V21_SMALL_RELEASE_SHA256, "").expect("midas"),
        (c, Recognition::Signature),
    ];
    for (c, _) in relative {
        assert!(!c.metric, "{} taken for metric", c.name);
    }
}

#[test]
fn dense_validate_names_the_mismatch() {
    let sig = pydnet_sig();
    let (good, _) = recognise(&sig, PYDNET_PP_SHA256, "").expect("known");
    let err = |c: ModelConfig| c.validate(&sig).expect_err("must not fit").to_string();
    let e = err(ModelConfig {
        input_width: 256,
        input_height: 256,
        ..good.clone()
    });
    assert!(e.contains("256x256") && e.contains("640x448"), "{e}");
    let e = err(ModelConfig {
        input: "pixel_values".into(),
        ..good.clone()
    });
    assert!(
        e.contains("no input `pixel_values`") && e.contains("`image`"),
        "{e}"
    );
    let e = err(ModelConfig {
        output: "depth".into(),
        ..good.clone()
    });
    assert!(
        e.contains("no output `depth`") && e.contains("depth_half"),
        "{e}"
    );
    let e = err(ModelConfig {
        layout: Layout::Nhwc,
        ..good.clone()
    });
    assert!(e.contains("channels"), "{e}");
    let e = err(ModelConfig {
        resize: ResizeMode::KeepAspect,
        ..good
    });
    assert!(e.contains("dynamic"), "{e}");
}

#[test]
fn dense_unknown_signature_is_not_recognised() {
    let sig = ModelSignature {
        inputs: vec![tensor("x", &[1, 3, 100, 100])],
        outputs: vec![tensor("y", &[1, 1, 100, 100])],
    };
    assert!(recognise(&sig, "00", "anything.onnx").is_none());
}
