// `import dyq._C` loads this library, whose static initializers register the dyq ops with torch. The
// module also carries the precision registry (common/precision.h) for Python, the GEMM width
// counters (torch/width_counts.h), the CPU path the kernels run (cpu/cpu_isa.h) and whose threads run
// them (parallel/parallel.h).
#include <Python.h>

#include <stdexcept>

#include "common/precision.h"
#include "cpu/cpu_isa.h"
#include "parallel/parallel.h"
#include "torch/width_counts.h"

namespace {

template <int... kValues>
PyObject* int_tuple(dyq::IntList<kValues...>) {
  PyObject* tuple = PyTuple_New(sizeof...(kValues));
  int index = 0;
  (PyTuple_SET_ITEM(tuple, index++, PyLong_FromLong(kValues)), ...);
  return tuple;
}

// (bits, codes per byte, levels) of each registered width: 0 codes and levels for the fallback.
template <int... kBits>
PyObject* traits_tuple(dyq::IntList<kBits...>) {
  PyObject* tuple = PyTuple_New(sizeof...(kBits));
  int index = 0;
  (PyTuple_SET_ITEM(tuple, index++,
                    Py_BuildValue("(iii)", kBits, dyq::ActivationTraits<kBits>::kCodesPerByte,
                                  dyq::ActivationTraits<kBits>::kLevels)),
   ...);
  return tuple;
}

PyObject* gemm_width_counts(PyObject*, PyObject*) {
  const auto counts = dyq::gemm_width_counts();
  PyObject* tuple = PyTuple_New(dyq::kNumActivationWidths);
  for (int i = 0; i < dyq::kNumActivationWidths; ++i) PyTuple_SET_ITEM(tuple, i, PyLong_FromLongLong(counts[i]));
  return tuple;
}

PyObject* reset_gemm_width_counts(PyObject*, PyObject*) {
  dyq::reset_gemm_width_counts();
  Py_RETURN_NONE;
}

// (active path, the paths this CPU can execute, the paths compiled in), each by its DYQ_CPU_ISA name.
PyObject* cpu_isa(PyObject*, PyObject*) {
  const char* active = nullptr;
  try {
    active = dyq::cpu::active_cpu_path().name;
  } catch (const std::invalid_argument& error) {
    PyErr_SetString(PyExc_ValueError, error.what());
    return nullptr;
  }
  const auto runnable = dyq::cpu::runnable_cpu_paths();
  const auto& compiled = dyq::cpu::cpu_paths();
  PyObject* runnable_names = PyTuple_New(static_cast<Py_ssize_t>(runnable.size()));
  for (size_t i = 0; i < runnable.size(); ++i) PyTuple_SET_ITEM(runnable_names, i, PyUnicode_FromString(runnable[i]->name));
  PyObject* compiled_names = PyTuple_New(static_cast<Py_ssize_t>(compiled.size()));
  for (size_t i = 0; i < compiled.size(); ++i) PyTuple_SET_ITEM(compiled_names, i, PyUnicode_FromString(compiled[i].name));
  return Py_BuildValue("(sNN)", active, runnable_names, compiled_names);
}

// The kernel the active path's GEMM runs for (m, k, group_size, act_bits), e.g. "avx512/panel-vnni".
PyObject* cpu_gemm_kernel(PyObject*, PyObject* args) {
  long long m = 0, k = 0;
  int group_size = 0, act_bits = 0;
  if (!PyArg_ParseTuple(args, "LLii", &m, &k, &group_size, &act_bits)) return nullptr;
  try {
    return PyUnicode_FromString(dyq::cpu::active_cpu_path().kernels->gemm_kernel(m, k, group_size, act_bits));
  } catch (const std::invalid_argument& error) {
    PyErr_SetString(PyExc_ValueError, error.what());
    return nullptr;
  }
}

// Whose threads run the CPU kernels: "torch" (its intra-op pool) or "dyq" (dyq's own pool).
PyObject* cpu_threads(PyObject*, PyObject*) {
  return PyUnicode_FromString(dyq::runs_on_host_threads() ? "torch" : "dyq");
}

PyMethodDef methods[] = {
    {"cpu_isa", cpu_isa, METH_NOARGS,
     "(active CPU path, paths this CPU can execute, paths compiled in), by their DYQ_CPU_ISA names."},
    {"cpu_gemm_kernel", cpu_gemm_kernel, METH_VARARGS,
     "cpu_gemm_kernel(m, k, group_size, act_bits): the kernel the active CPU path's GEMM runs for them."},
    {"cpu_threads", cpu_threads, METH_NOARGS,
     "Whose threads run the CPU kernels: \"torch\" (its intra-op pool) or \"dyq\" (dyq's own pool)."},
    {"gemm_width_counts", gemm_width_counts, METH_NOARGS,
     "GEMM calls of this process per registered activation width, in the order of ACTIVATION_BITS."},
    {"reset_gemm_width_counts", reset_gemm_width_counts, METH_NOARGS, "Set every GEMM width count to 0."},
    {nullptr, nullptr, 0, nullptr}};

}  // namespace

extern "C" PyObject* PyInit__C(void) {
  static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_C", "dyq's compiled operators", -1, methods};
  PyObject* m = PyModule_Create(&module);
  if (m == nullptr) return nullptr;
  PyModule_AddObject(m, "ACTIVATION_BITS", int_tuple(dyq::RegisteredActivationBits()));
  PyModule_AddObject(m, "ACTIVATION_TRAITS", traits_tuple(dyq::RegisteredActivationBits()));
  PyModule_AddObject(m, "GROUP_SIZES", int_tuple(dyq::RegisteredGroupSizes()));
  PyModule_AddIntConstant(m, "FALLBACK_BITS", dyq::kFallbackBits);
  return m;
}
