//! candle-transformers' Stable Diffusion UNet, the yardstick of our SD2-family UNet: the config
//! of theirs that builds the same network as one of ours. Shared by tests/marigold_unet.rs and
//! examples/bench_unet.rs (included there by path).
use candle_transformers::models::stable_diffusion::unet_2d as reference;
use pixl_estimate::marigold::config::DownBlockType;
use pixl_estimate::marigold::UnetConfig;

/// The same network in candle-transformers' terms.
pub fn reference_config(cfg: &UnetConfig) -> reference::UNet2DConditionModelConfig {
    let blocks = (0..cfg.block_out_channels.len())
        .map(|i| reference::BlockConfig {
            out_channels: cfg.block_out_channels[i],
            use_cross_attn: (cfg.down_block_types[i] == DownBlockType::CrossAttnDownBlock2D)
                .then_some(cfg.transformer_layers_per_block[i]),
            attention_head_dim: cfg.attention_head_dim[i],
        })
        .collect();
    reference::UNet2DConditionModelConfig {
        center_input_sample: cfg.center_input_sample,
        flip_sin_to_cos: cfg.flip_sin_to_cos,
        freq_shift: cfg.freq_shift,
        blocks,
        layers_per_block: cfg.layers_per_block[0],
        downsample_padding: cfg.downsample_padding,
        mid_block_scale_factor: cfg.mid_block_scale_factor,
        norm_num_groups: cfg.norm_num_groups,
        norm_eps: cfg.norm_eps,
        cross_attention_dim: cfg.cross_attention_dim,
        sliced_attention_size: None,
        use_linear_projection: cfg.use_linear_projection,
    }
}
