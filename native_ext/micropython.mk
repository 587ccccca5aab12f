# dr_native as a user C module (make USER_C_MODULES=... in a port's folder)
DR_NATIVE_DIR := $(USERMOD_DIR)

SRC_USERMOD += $(DR_NATIVE_DIR)/dr_native.c
SRC_USERMOD += $(DR_NATIVE_DIR)/dr_kernel.c
SRC_USERMOD += $(DR_NATIVE_DIR)/dr_median.c
SRC_USERMOD += $(DR_NATIVE_DIR)/dr_geo.c
SRC_USERMOD += $(DR_NATIVE_DIR)/dr_fused.c
include $(DR_NATIVE_DIR)/dr_sources.mk
SRC_USERMOD += $(addprefix $(DR_NATIVE_DIR)/,$(DR_ALGORITHM_SRC))

CFLAGS_USERMOD += -I$(DR_NATIVE_DIR)
