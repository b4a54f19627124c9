//! The checkpoint loader (safetensors header, config metadata, name/shape/dtype validation) on
//! arbitrary bytes: must return `Ok` or `Err`, never panic.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let tmp = std::env::temp_dir().join(format!("pixl-fuzz-w-{}.safetensors", std::process::id()));
    if std::fs::write(&tmp, data).is_ok() {
        let _ = pixl_model::checkpoint::read_config(&tmp);
        let _ = pixl_model::checkpoint::load(&tmp, &candle_core::Device::Cpu, candle_core::DType::F32);
    }
});
