// `import dyq._C` loads this library, whose static initializers register the dyq ops with torch.
#include <Python.h>

extern "C" PyObject* PyInit__C(void) {
  static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_C", "dyq's compiled operators", -1, nullptr};
  return PyModule_Create(&module);
}
