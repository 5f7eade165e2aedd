#pragma once
// Vision pipeline settings ([vision] in a part recipe).
namespace fettle::config {

struct VisionSettings {};

}  // namespace fettle::config
