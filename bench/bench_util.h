// What the C++ benchmarks under bench/ share: the median of timings and the CPU's name for their JSON.
#pragma once

#include <algorithm>
#include <cstdio>
#include <cstring>
#include <string>
#include <vector>

namespace dyq::bench {

inline double median(std::vector<double> values) {
  std::sort(values.begin(), values.end());
  return values[values.size() / 2];
}

// The model name of the first CPU in /proc/cpuinfo, or "unknown".
inline std::string cpu_model() {
  FILE* file = std::fopen("/proc/cpuinfo", "r");
  if (file == nullptr) return "unknown";
  char line[512];
  std::string model = "unknown";
  while (std::fgets(line, sizeof(line), file) != nullptr) {
    if (std::strncmp(line, "model name", 10) == 0) {
      const char* value = std::strchr(line, ':');
      if (value != nullptr) model = std::string(value + 2, std::strcspn(value + 2, "\n"));
      break;
    }
  }
  std::fclose(file);
  return model;
}

}  // namespace dyq::bench
