# dr_native as a user C module for the CMake ports (ESP32, RP2): idf.py -D USER_C_MODULES=.../micropython.cmake
add_library(usermod_dr_native INTERFACE)

target_sources(usermod_dr_native INTERFACE
    ${CMAKE_CURRENT_LIST_DIR}/dr_native.c
    ${CMAKE_CURRENT_LIST_DIR}/dr_kernel.c
    ${CMAKE_CURRENT_LIST_DIR}/dr_median.c
    ${CMAKE_CURRENT_LIST_DIR}/dr_geo.c
    ${CMAKE_CURRENT_LIST_DIR}/dr_fused.c
    # the error-state filter: compiled always (dr_native.c calls it only where dr_board.h's DR_WITH_ESKF is 1; the
    # firmware's link drops what nothing calls)
    ${CMAKE_CURRENT_LIST_DIR}/dr_eskf.c
)

target_include_directories(usermod_dr_native INTERFACE
    ${CMAKE_CURRENT_LIST_DIR}
)

target_link_libraries(usermod INTERFACE usermod_dr_native)
