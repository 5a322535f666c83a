// tiny_model.hpp - the small MA-DBP configuration the model and sampler tests share: every
// part present (AAP or LE, local crops, two U-Net levels), fast enough for finite differences.
#pragma once
#include "madbp.hpp"

inline madbp::ModelConfig tiny_config(madbp::Processor p = madbp::Processor::AAP) {
    madbp::ModelConfig c;
    c.horizon = 8;
    c.dim = 8;
    c.heads = 2;
    c.n_max = 6;
    c.grid = 8;
    c.local_grid = 8;
    c.channels = {4, 6};
    c.kernel = 3;
    c.diffusion_steps = 20;
    c.sample_steps = 5;
    c.processor = p;
    return c;
}
