# Run after linking dyq._C (cmake -DNM=... -DMODULE=... -DCOMPILER=... -P this file): fails when the module
# carries its own copy of libstdc++. torch uses the shared one, and two copies in one process crash at the
# first locale-dependent stream write (an error message that formats a number). A compiler whose driver
# links libstdc++ statically into shared objects does this; seen with a /opt/gcc toolchain on a GPU image.
execute_process(COMMAND ${NM} --defined-only ${MODULE} OUTPUT_VARIABLE _symbols ERROR_QUIET RESULT_VARIABLE _rc)
if(_rc EQUAL 0 AND _symbols MATCHES "_ZNSt6locale7classicEv")  # std::locale::classic(), defined by libstdc++
  file(REMOVE ${MODULE})
  message(FATAL_ERROR "dyq: ${COMPILER} linked a static copy of libstdc++ into ${MODULE}, beside the shared "
                      "libstdc++ that torch uses: the two crash together at the first formatted error message. "
                      "Build with a compiler that links libstdc++.so, e.g. CXX=/usr/bin/g++ CUDAHOSTCXX=/usr/bin/g++ "
                      "pip install --no-build-isolation --no-deps .")
endif()
