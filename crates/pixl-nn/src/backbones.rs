//! Pretrained CNN feature extractors in torchvision layout (VGG16, AlexNet) for the perceptual
//! loss and LPIPS. (Filled in by the evaluation work.)
