# ctsmTMB's one-step-ahead residuals of its Laplace method on the first 50 rows of its Ornstein2D data, for
# tests/test_crosscheck.py::test_laplace_one_step_residuals_match_ctsmtmb.
#
#   R_LIBS=<ctsmTMB 1.1.1 library> Rscript benchmarks/ctsmtmb_one_step.R OUT_FOLDER
#
# Writes OUT_FOLDER/par.csv (the Laplace estimates) and OUT_FOLDER/residuals.csv: RTMB::oneStepPredict with
# method "oneStepGaussian", as estimate(laplace.residuals = TRUE) runs it; its rows are the observations output
# by output (y1 at every row, then y2), the order each is conditioned in.
suppressPackageStartupMessages(library(ctsmTMB))
out <- commandArgs(trailingOnly = TRUE)[1]
dir.create(out, showWarnings = FALSE, recursive = TRUE)
data(Ornstein2D, package = "ctsmTMB")
d <- Ornstein2D[1:50, ]
m <- create.Ornstein2D.model()
fit <- m$estimate(d, method = "laplace", silent = TRUE, trace = 0)
res <- RTMB::oneStepPredict(m$.__enclos_env__$private$nll, observation.name = "obsMat",
                            method = "oneStepGaussian", trace = FALSE, parallel = TRUE)
write.csv(data.frame(name = names(fit$par.fixed), value = fit$par.fixed), file.path(out, "par.csv"),
          row.names = FALSE)
write.csv(as.data.frame(res), file.path(out, "residuals.csv"), row.names = FALSE)
