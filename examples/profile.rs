//! Where the time of one 224x224 search forward goes, stage by stage (burn's generic ops; the
//! fused CPU paths replace some of them in the real forward).
//! `cargo run --release --example profile [batch] [--whole] [--size N] [--bf16]` (search image
//! N x N, default 224; `--bf16`: the network's products in bf16).

use std::time::Instant;

/// As in the binary (see `src/main.rs`).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

use burn::prelude::*;
use burn::tensor::Distribution;
use posematch::model::{InferenceNetwork, TdcmConfig, depthwise_correlation, select_device};

fn time<F: FnMut() -> Tensor<4>>(name: &str, runs: usize, mut f: F) -> Tensor<4> {
    // flex executes eagerly: an op's cost is paid when the call returns (views such as permute
    // are free and their cost lands on the consumer), so no read-back is needed.
    let mut out = f();
    let start = Instant::now();
    for _ in 0..runs {
        out = f();
    }
    println!(
        "{name:28} {:8.2} ms",
        start.elapsed().as_secs_f64() * 1e3 / runs as f64
    );
    out
}

fn main() {
    // `profile [batch] [--whole]`: `--whole` times only the full forward (for `perf record`).
    let args: Vec<String> = std::env::args().skip(1).collect();
    let whole_only = args.iter().any(|a| a == "--whole");
    let size: usize = args
        .iter()
        .position(|a| a == "--size")
        .and_then(|i| args.get(i + 1)?.parse().ok())
        .unwrap_or(224);
    let batch: usize = args
        .iter()
        .enumerate()
        .filter(|&(i, _)| i == 0 || args[i - 1] != "--size")
        .find_map(|(_, a)| a.parse().ok())
        .unwrap_or(1);
    let device = select_device().unwrap();
    let model = TdcmConfig::new().init(&device);
    let m = &model.search_matcher;
    // What the matcher runs: the CPU implementation on flex/ndarray.
    let precision = if args.iter().any(|a| a == "--bf16") {
        posematch::model::Precision::Bf16
    } else {
        posematch::model::Precision::F32
    };
    let network = InferenceNetwork::new(model.clone(), &device)
        .with_precision(precision)
        .expect("precision available on this machine");
    let runs = 10;
    let images = Tensor::<4>::random(
        [batch, 3, size, size],
        Distribution::Normal(0.0, 1.0),
        &device,
    );
    let template = Tensor::<4>::random([batch, 3, 36, 36], Distribution::Normal(0.0, 1.0), &device);
    let kernels = time("template encoder", runs, || {
        network.encode_templates(template.clone())
    });
    if whole_only {
        let _ = time("whole search forward", 30, || {
            network.forward(images.clone(), kernels.clone()).stacked
        });
        return;
    }
    let b = &m.backbone;
    let x = time("stem conv", runs, || b.stem_conv.forward(images.clone()));
    let x = time("stem norm (permute+LN)", runs, || {
        b.stem_norm
            .forward(x.clone().permute([0, 2, 3, 1]))
            .permute([0, 3, 1, 2])
    });
    let mut y = x.clone();
    for (i, block) in b.blocks.iter().enumerate() {
        let input = y.clone();
        let d = time(&format!("block{i} dwconv7x7"), runs, || {
            block.conv_dw.forward(input.clone())
        });
        let n = time(&format!("block{i} permute+LN"), runs, || {
            block.norm.forward(d.clone().permute([0, 2, 3, 1]))
        });
        let f1 = time(&format!("block{i} fc1"), runs, || {
            block.fc1.forward(n.clone())
        });
        let g = time(&format!("block{i} gelu"), runs, || {
            block.activation.forward(f1.clone())
        });
        let r = time(&format!("block{i} grn"), runs, || {
            block.grn.forward(g.clone())
        });
        let _ = time(&format!("block{i} fused gelu+grn"), runs, || {
            posematch::model::cpu::gelu_grn(
                f1.clone(),
                block.grn.weight.val(),
                block.grn.bias.val(),
                1e-6,
            )
        });
        let f2 = time(&format!("block{i} fc2"), runs, || {
            block.fc2.forward(r.clone())
        });
        y = time(&format!("block{i} permute+residual"), runs, || {
            input.clone() + f2.clone().permute([0, 3, 1, 2])
        });
    }
    let features = time("batch norm", runs, || b.norm.forward(y.clone()));
    let corr = time("correlation", runs, || {
        depthwise_correlation(features.clone(), kernels.clone())
    });
    let fusion = time("fusion conv3x3", runs, || m.fusion.forward(corr.clone()));
    let d = &m.decoder;
    let c1 = time("conv1+bn1", runs, || {
        d.bn1.forward(d.conv1.forward(fusion.clone()))
    });
    let s1 = time("relu+shuffle", runs, || {
        d.shuffle
            .forward(burn::tensor::activation::relu(c1.clone()))
    });
    let c2 = time("conv2+bn2", runs, || {
        d.bn2.forward(d.conv2.forward(s1.clone()))
    });
    let s2 = time("relu+shuffle", runs, || {
        d.shuffle
            .forward(burn::tensor::activation::relu(c2.clone()))
    });
    let _ = time("one head", runs, || {
        m.heads
            .score
            .conv1x1
            .forward(burn::tensor::activation::relu(
                m.heads.score.conv3x3.forward(s2.clone()),
            ))
    });
    let _ = time("fused heads", runs, || m.heads.forward(s2.clone()));
    {
        use burn::tensor::module::conv2d;
        use burn::tensor::ops::ConvOptions;
        let w3 = Tensor::<4>::random([60, 24, 3, 3], Distribution::Normal(0.0, 0.1), &device);
        let b3 = Tensor::<1>::zeros([60], &device);
        let h = time("heads conv3x3 24->60", runs, || {
            conv2d(
                s2.clone(),
                w3.clone(),
                Some(b3.clone()),
                ConvOptions::new([1, 1], [1, 1], [1, 1], 1),
            )
        });
        let r = time("heads relu", runs, || {
            burn::tensor::activation::relu(h.clone())
        });
        let w1 = Tensor::<4>::random([5, 12, 1, 1], Distribution::Normal(0.0, 0.1), &device);
        let b1 = Tensor::<1>::zeros([5], &device);
        let _ = time("heads grouped 1x1", runs, || {
            conv2d(
                r.clone(),
                w1.clone(),
                Some(b1.clone()),
                ConvOptions::new([1, 1], [0, 0], [1, 1], 5),
            )
        });
        let w1d = Tensor::<4>::random([5, 60, 1, 1], Distribution::Normal(0.0, 0.1), &device);
        let _ = time("heads dense 1x1 60->5", runs, || {
            conv2d(
                r.clone(),
                w1d.clone(),
                Some(b1.clone()),
                ConvOptions::new([1, 1], [0, 0], [1, 1], 1),
            )
        });
        let c2w = Tensor::<4>::random([96, 48, 3, 3], Distribution::Normal(0.0, 0.1), &device);
        let _ = time("conv2 alone", runs, || {
            conv2d(
                s1.clone(),
                c2w.clone(),
                None,
                ConvOptions::new([1, 1], [1, 1], [1, 1], 1),
            )
        });
    }
    let _ = time("whole search forward", runs, || {
        network.forward(images.clone(), kernels.clone()).stacked
    });
}
